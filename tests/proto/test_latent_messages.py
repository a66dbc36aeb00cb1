"""FLAM's labels of the workers' stream (ch. 8): LatentActions round-trips exactly and is refused off-contract."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from proto import topics
from proto.codec import ProtocolError, decode, encode
from proto.messages import MESSAGE_TYPES, LatentActions
from tests.proto.samples import latent_actions


def test_registered_and_round_trips_exactly() -> None:
    assert MESSAGE_TYPES["LatentActions"] is LatentActions
    want = latent_actions()
    got = decode(encode(want), LatentActions)
    assert (got.kind, got.worker_id, got.seq, got.weights_version, len(got)) == ("flam", "w0", 7, 3, 4)
    for name in ("episode_id", "step", "mean", "log_sigma"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
        assert getattr(got, name).dtype == getattr(want, name).dtype


@pytest.mark.parametrize("changes, reason", [
    (dict(log_sigma=np.zeros((4, 3, 3), np.float32)), "inconsistent"),
    (dict(step=np.arange(3, dtype=np.int32)), "inconsistent"),
    (dict(episode_id=np.arange(5, dtype=np.int64)), "inconsistent"),
    (dict(mean=np.zeros((0, 3, 2), np.float32), log_sigma=np.zeros((0, 3, 2), np.float32)), "bad_field"),
    (dict(mean=np.zeros((4, 0, 2), np.float32), log_sigma=np.zeros((4, 0, 2), np.float32)), "bad_field"),
    (dict(mean=np.zeros((4, 3), np.float32)), "bad_array"),
    (dict(mean=np.full((4, 3, 2), np.nan, np.float32)), "non_finite"),
    (dict(step=np.arange(4, dtype=np.int64)), "bad_array"),
    (dict(seq=-1), "bad_field"),
    (dict(weights_version=-2), "bad_field"),
    (dict(worker_id="w/0"), "bad_field"),
    (dict(kind=""), "bad_field"),
])
def test_off_contract_is_refused(changes: dict, reason: str) -> None:
    with pytest.raises(ProtocolError) as info:
        decode(encode(replace(latent_actions(), **changes)))
    assert info.value.reason == reason


def test_topic() -> None:
    assert topics.latent_actions("r", "w0") == "causeway/r/latent/w0"
    assert topics.latent_actions("r") == "causeway/r/latent/*"
