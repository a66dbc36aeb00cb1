"""FrameBatch (the frames topic): exact round trip, and refusal of frames that do not hold together."""
from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import pytest

from proto import FrameBatch, decode, encode, topics
from tests.proto.samples import assert_same, frame_batch, raw_of, reason_of, wire


def test_round_trip_is_exact() -> None:
    batch = frame_batch()
    back = decode(encode(batch), FrameBatch)
    assert_same(batch, back)
    assert len(back) == 4 and back.frames.dtype == np.uint8 and back.frames.flags.writeable


def test_round_trip_without_labels() -> None:
    batch = frame_batch()
    batch = FrameBatch(**{**batch.__dict__, "labels": None})
    assert decode(encode(batch), FrameBatch).labels is None


def _with(**changes: Any) -> bytes:
    raw = raw_of(frame_batch())
    for name, value in changes.items():
        raw[name] = wire(value) if isinstance(value, np.ndarray) else value
    return msgpack.packb(raw, use_bin_type=True)


@pytest.mark.parametrize("changes, reason", [
    ({"state_frame": np.array([0, 1, 3, 6], np.int32)}, "inconsistent"),  # frame 6 of 6
    ({"next_frame": np.array([1, 2, 4, -1], np.int32)}, "inconsistent"),
    ({"state_frame": np.array([0, 1, 3], np.int32)}, "inconsistent"),  # 3 indices for 4 steps
    ({"frames": np.zeros((6, 8, 8, 4), np.uint8)}, "inconsistent"),  # RGBA
    ({"frames": np.zeros((9, 8, 8, 3), np.uint8)}, "inconsistent"),  # more than 2T frames
    ({"frames": np.zeros((6, 8, 8, 3), np.float32)}, "bad_array"),
    ({"frames": np.zeros((6, 8, 8), np.uint8)}, "bad_array"),
    ({"labels": np.zeros((6, 8, 7), np.uint8)}, "inconsistent"),
    ({"reward": np.zeros(3, np.float32)}, "inconsistent"),
    ({"action": np.zeros((3, 1), np.float32)}, "inconsistent"),
    ({"state_frame": np.zeros(4, np.int64)}, "bad_array"),
    ({"worker_id": "w/0"}, "bad_field"),
    ({"seq": -1}, "bad_field"),
    ({"labels": "none"}, "bad_field"),
])
def test_malformed_frames_are_refused(changes: dict[str, Any], reason: str) -> None:
    assert reason_of(_with(**changes), FrameBatch) == reason


def test_missing_and_extra_fields_are_refused() -> None:
    raw = raw_of(frame_batch())
    del raw["next_frame"]
    assert reason_of(msgpack.packb(raw, use_bin_type=True)) == "bad_field"
    assert reason_of(_with(extra=1)) == "bad_field"
    assert reason_of(_with(schema_version=1)) == "bad_version"


def test_frames_topics() -> None:
    assert topics.frames("r1", "w0") == "causeway/r1/frames/w0"
    assert topics.frames("r1") == "causeway/r1/frames/*"
    assert topics.frames_spec("r1") == "causeway/r1/env/frames" != topics.env_spec("r1")
    with pytest.raises(ValueError):
        topics.frames("r1", "a/b")
