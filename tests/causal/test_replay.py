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


def test_rewards_are_kept_sampled_on_request_and_checkpointed() -> None:
    import numpy as np

    from causal.replay import ReplayBuffer

    replay = ReplayBuffer(4, 2, 1, seed=0)
    states = np.arange(12, dtype=np.float32).reshape(6, 2)
    replay.add(states, states[:, :1], states + 1, reward=np.arange(6, dtype=np.float32))
    assert sorted(replay.reward.tolist()) == [2.0, 3.0, 4.0, 5.0]  # the newest four rows
    s, a, n, r = replay.sample(16, with_reward=True)
    assert len(replay.sample(16)) == 3 and (r.numpy() == s.numpy()[:, 0] / 2).all()
    saved = replay.state_dict()
    older = {k: v for k, v in saved.items() if k != "reward"}  # a checkpoint from before rewards were kept
    again = ReplayBuffer(4, 2, 1)
    again.load_state_dict(older)
    assert (again.reward == 0).all() and (again.state == replay.state).all()
    again.load_state_dict(saved)
    assert (again.reward == replay.reward).all()
