"""SkiLD's messages (ch. 6): SkillBatch and InducedGraphs round-trip exactly and are refused off-contract."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from proto import topics
from proto.codec import ProtocolError, decode, encode
from proto.messages import MESSAGE_TYPES, InducedGraphs, SkillBatch
from tests.proto.samples import transitions


def skill_batch(**changes) -> SkillBatch:
    batch = SkillBatch(transitions(), "pretrain", np.array([0, 0, -1, 3], np.int32), np.array([1, 1, 2, 0], np.int32),
                       np.array([True, False, True, True]))
    return replace(batch, **changes)


def induced(**changes) -> InducedGraphs:
    graphs = np.random.default_rng(1).integers(0, 2, size=(4, 3, 4), dtype=np.uint8)
    return replace(InducedGraphs("skild", "w0", 7, 2, graphs), **changes)


def test_registered_and_round_trip_exactly() -> None:
    assert MESSAGE_TYPES["SkillBatch"] is SkillBatch and MESSAGE_TYPES["InducedGraphs"] is InducedGraphs
    got = decode(encode(skill_batch()), SkillBatch)
    want = skill_batch()
    assert got.phase == "pretrain" and got.transitions.seq == want.transitions.seq
    for name in ("slot", "b", "started"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
        assert getattr(got, name).dtype == getattr(want, name).dtype
    np.testing.assert_array_equal(got.transitions.state, want.transitions.state)
    g = decode(encode(induced()), InducedGraphs)
    assert (g.kind, g.worker_id, g.seq, g.weights_version) == ("skild", "w0", 7, 2)
    np.testing.assert_array_equal(g.graphs, induced().graphs)


@pytest.mark.parametrize("bad, reason", [
    (lambda: skill_batch(phase="finetune"), "bad_field"),
    (lambda: skill_batch(slot=np.array([0, -2, 0, 0], np.int32)), "bad_array"),
    (lambda: skill_batch(b=np.array([0, -1, 0, 0], np.int32)), "bad_array"),
    (lambda: skill_batch(started=np.ones(3, bool)), "inconsistent"),
    (lambda: skill_batch(slot=np.zeros(4, np.int64)), "bad_array"),
    (lambda: induced(graphs=np.zeros((4, 3, 3), np.uint8)), "inconsistent"),
    (lambda: induced(graphs=np.full((4, 3, 4), 2, np.uint8)), "bad_array"),
    (lambda: induced(graphs=np.zeros((0, 3, 4), np.uint8)), "bad_field"),
    (lambda: induced(seq=-1), "bad_field"),
    (lambda: induced(worker_id="w/0"), "bad_field"),
])
def test_off_contract_is_refused(bad, reason: str) -> None:
    with pytest.raises(ProtocolError) as info:
        decode(encode(bad()))
    assert info.value.reason == reason


def test_topics() -> None:
    assert topics.skills("r", "w0") == "causeway/r/skills/w0"
    assert topics.induced("r", "skild", "w0") == "causeway/r/induced/skild/w0"
    with pytest.raises(ValueError):
        topics.skills("r", "a/b")
