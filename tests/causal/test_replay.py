"""Replay ring buffer and the episode-level held-out split."""
from __future__ import annotations

import numpy as np

from causal.replay import ReplayBuffer, heldout_mask


def test_heldout_split_is_by_episode_deterministic_and_near_fraction() -> None:
    episodes = np.repeat(np.arange(5000), 3)
    mask = heldout_mask("w0", episodes, 0.1)
    assert (mask.reshape(-1, 3).all(axis=1) | ~mask.reshape(-1, 3).any(axis=1)).all()
    assert 0.08 < mask.mean() < 0.12
    assert (mask == heldout_mask("w0", episodes, 0.1)).all()
    assert (mask != heldout_mask("w1", episodes, 0.1)).any()
    assert not heldout_mask("w0", episodes, 0.0).any()


def test_ring_buffer_overwrites_oldest_and_round_trips() -> None:
    buf = ReplayBuffer(5, state_dim=2, action_dim=1)
    for start in (0, 3, 6):
        rows = np.arange(start, start + 3, dtype=np.float32)
        buf.add(np.stack([rows, rows], 1), rows[:, None], np.stack([rows, rows], 1) + 1)
    assert buf.size == 5 and buf.added == 9
    assert sorted(buf.state[:, 0].tolist()) == [4, 5, 6, 7, 8]
    clone = ReplayBuffer(5, 2, 1)
    clone.load_state_dict(buf.state_dict())
    assert clone.size == 5 and (clone.state == buf.state).all() and clone.cursor == buf.cursor
    s, a, n = buf.sample(7)
    assert s.shape == (7, 2) and (n - s == 1).all()


def test_a_wrapped_ring_restored_into_a_larger_one_keeps_its_newest_rows() -> None:
    small = ReplayBuffer(5, state_dim=1, action_dim=1)
    for start in (0, 3, 6):  # rows 4..8 kept, the cursor mid-ring
        rows = np.arange(start, start + 3, dtype=np.float32)[:, None]
        small.add(rows, rows, rows)
    large = ReplayBuffer(8, 1, 1)
    large.load_state_dict(small.state_dict())
    assert large.size == 5 and large.state[:5, 0].tolist() == [4, 5, 6, 7, 8] and large.cursor == 5
    more = np.array([[9], [10], [11], [12]], np.float32)
    large.add(more, more, more)  # fills the new room, then overwrites the oldest (4), not the newest
    assert large.size == 8 and sorted(large.state[:, 0].tolist()) == list(range(5, 13))
