"""Replay ring buffer and the episode-level held-out split."""
from __future__ import annotations

import numpy as np
import pytest

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


def _prioritised(rows: int, capacity: int | None = None, seed: int = 0):
    from causal.replay import PrioritisedReplay

    buf = PrioritisedReplay(capacity or rows, state_dim=1, action_dim=1, seed=seed)
    values = np.arange(rows, dtype=np.float32)[:, None]
    buf.add(values, values, values + 1)
    return buf


def test_prioritised_replay_samples_in_proportion_to_priorities() -> None:
    buf = _prioritised(6)
    priorities = np.array([1.0, 0.5, 4.0, 0.25, 2.0, 0.25])
    buf.update_priorities(np.arange(6), priorities)
    draws = np.concatenate([buf.sample_indexed(64)[0] for _ in range(500)])
    expected = priorities / priorities.sum()
    frequency = np.bincount(draws, minlength=6) / len(draws)
    np.testing.assert_allclose(frequency, expected, atol=0.01)  # 32,000 stratified draws
    np.testing.assert_allclose(buf.probabilities(), expected)
    index, (s, a, n) = buf.sample_indexed(16)
    assert (s[:, 0].numpy() == index).all() and (n - s == 1).all()


def test_prioritised_replay_gives_new_rows_the_largest_priority_and_refuses_bad_ones() -> None:
    buf = _prioritised(4, capacity=8)
    buf.update_priorities(np.array([0, 1]), np.array([3.0, 0.5]))
    more = np.array([[9.0], [10.0]], np.float32)
    buf.add(more, more, more)
    np.testing.assert_allclose(buf.priorities.get(np.arange(6)), [3.0, 0.5, 1.0, 1.0, 3.0, 3.0])
    with pytest.raises(ValueError, match="positive"):
        buf.update_priorities(np.array([0]), np.array([0.0]))


def test_prioritised_replay_round_trips_its_priorities_through_a_checkpoint() -> None:
    from causal.replay import PrioritisedReplay

    buf = _prioritised(7, capacity=5)  # wrapped: rows 2..6 remain
    buf.update_priorities(np.arange(5), np.array([1.0, 2.0, 3.0, 4.0, 5.0]))
    rows_by_value = {float(buf.state[k, 0]): buf.priorities.get(np.array([k]))[0] for k in range(5)}
    bigger = PrioritisedReplay(10, 1, 1)
    bigger.load_state_dict(buf.state_dict())
    restored = {float(bigger.state[k, 0]): bigger.priorities.get(np.array([k]))[0] for k in range(bigger.size)}
    assert restored == rows_by_value and bigger.max_priority == 5.0
    plain = PrioritisedReplay(5, 1, 1)
    plain.load_state_dict(ReplayBuffer(5, 1, 1).state_dict() | {"state": buf.state_dict()["state"],
                                                                  "action": buf.state_dict()["action"],
                                                                  "next_state": buf.state_dict()["next_state"],
                                                                  "reward": buf.state_dict()["reward"], "added": 5})
    np.testing.assert_allclose(plain.probabilities(), np.full(5, 0.2))  # a checkpoint without priorities


def _walk(start: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of one episode whose state counts up: state t, next_state t + 1."""
    values = start + np.arange(steps + 1, dtype=np.float32)
    return values[:-1, None], values[1:, None]


def test_clips_are_consecutive_states_that_never_span_an_episode_end_or_the_rings_seam() -> None:
    buffer = ReplayBuffer(capacity=40, state_dim=1, action_dim=1, seed=0)
    for start, steps in ((0.0, 6), (100.0, 2), (200.0, 9)):  # three episodes; the second too short for 4 frames
        state, next_state = _walk(start, steps)
        buffer.add(state, np.zeros((steps, 1), np.float32), next_state)
    clips = buffer.sample_clips(64, 4).numpy()[..., 0]
    assert clips.shape == (64, 4)
    assert np.all(np.diff(clips, axis=1) == 1.0)  # consecutive: never across an episode's end
    assert set(clips[:, 0]) <= {0.0, 1.0, 2.0, 3.0, 200.0, 201.0, 202.0, 203.0, 204.0, 205.0, 206.0}
    assert len(set(clips[:, 0])) > 5  # drawn across the whole buffer
    # a full, wrapped ring: the newest rows (300...) follow the oldest kept ones only in time, never in a clip
    state, next_state = _walk(300.0, 30)
    buffer.add(state, np.zeros((30, 1), np.float32), next_state)
    wrapped = buffer.sample_clips(256, 3).numpy()[..., 0]
    assert np.all(np.diff(wrapped, axis=1) == 1.0) and 329.0 in wrapped[:, -1]


def test_clips_are_refused_where_none_is_whole() -> None:
    buffer = ReplayBuffer(capacity=10, state_dim=1, action_dim=1, seed=0)
    with pytest.raises(ValueError, match="stored rows"):
        buffer.sample_clips(4, 3)
    for start in (0.0, 10.0, 20.0):  # one-step episodes: no two rows follow each other
        state, next_state = _walk(start, 1)
        buffer.add(state, np.zeros((1, 1), np.float32), next_state)
    assert buffer.sample_clips(4, 2).shape == (4, 2, 1)
    with pytest.raises(ValueError, match="no run of 2 consecutive transitions"):
        buffer.sample_clips(4, 3)
    with pytest.raises(ValueError, match="at least 2 frames"):
        buffer.sample_clips(4, 1)
