"""Decisions of a policy over skills stitched from step batches: returns, episode ends, gaps."""
from __future__ import annotations

import numpy as np
import pytest

from proto.codec import ProtocolError
from proto.messages import TransitionBatch
from services.policy_learner.options import OptionStitcher


def batch(seq: int, option: list[int], *, start: int = 0, ends: dict[int, str] | None = None,
          worker: str = "w0") -> TransitionBatch:
    """Steps ``start .. start + T - 1``: state = step index, next_state = index + 0.5 (so every
    observation names its step), ``ends``: step -> 'terminated' or 'truncated'."""
    t = len(option)
    steps = np.arange(start, start + t, dtype=np.float32)[:, None]
    flags = {name: np.array([(ends or {}).get(i) == name for i in range(t)]) for name in ("terminated", "truncated")}
    return TransitionBatch(worker_id=worker, seq=seq, policy_version=1, state=steps, action=np.zeros((t, 1), np.float32),
                           reward=np.zeros(t, np.float32), next_state=steps + 0.5, episode_id=np.zeros(t, np.int64),
                           step=np.arange(t, dtype=np.int32), option=np.array(option, np.int32), **flags)


def log_probs(obs: np.ndarray, options: np.ndarray) -> np.ndarray:
    return -(obs[:, 0] + options / 10)  # names the observation and option it was asked for


def test_decisions_sum_their_skill_rewards_across_batches() -> None:
    stitcher = OptionStitcher(length=2)
    reward = np.array([1.0, 2.0, 3.0, 4.0])
    assert stitcher.add(batch(0, [2, -1, -1, 5]), reward, log_probs) == []  # one finished, one running
    runs = stitcher.add(batch(1, [-1, 0, -1, -1], start=4), np.array([10.0, 20.0, 30.0, 40.0]), log_probs)
    assert len(runs) == 1
    first, second = runs[0]
    assert (first.option, first.reward, first.steps, first.obs[0], first.next_obs[0]) == (2, 6.0, 3, 0.0, 3.0)
    assert first.log_prob == pytest.approx(-0.2)
    # the second skill started at step 3 and ran into the next batch, until the decision at step 5
    assert (second.option, second.reward, second.steps, second.obs[0], second.next_obs[0]) == (5, 14.0, 2, 3.0, 5.0)
    assert second.log_prob == pytest.approx(-3.5)
    assert not (first.done or second.done or first.truncated)
    assert stitcher.streams["w0"].running.option == 0 and stitcher.decisions == 2
    assert stitcher.mean_returns() == {2: 6.0, 5: 14.0}


def test_episode_end_closes_the_decision_and_bootstraps_only_truncations() -> None:
    stitcher = OptionStitcher(length=3)
    runs = stitcher.add(batch(0, [1, -1, 4, -1, -1, 3, -1, -1], ends={1: "terminated", 4: "truncated"}),
                        np.ones(8), log_probs)
    assert runs == []
    done = stitcher.streams["w0"].finished
    assert [(d.option, d.reward, d.done, d.truncated, d.next_obs[0]) for d in done] == [
        (1, 2.0, True, False, 1.5),  # terminated: next_state of the last step, no bootstrap
        (4, 3.0, True, True, 4.5),  # time limit: bootstrapped from the state after it
    ]
    assert stitcher.streams["w0"].running.option == 3


def test_steps_before_the_first_seen_decision_are_skipped() -> None:
    stitcher = OptionStitcher(length=1)
    runs = stitcher.add(batch(4, [-1, -1, 6, -1, 1]), np.ones(5), log_probs)
    assert [(d.option, d.reward, d.obs[0]) for run in runs for d in run] == [(6, 2.0, 2.0)]


def test_a_gap_discards_the_running_decision_and_cuts_the_chain() -> None:
    stitcher = OptionStitcher(length=4)
    stitcher.add(batch(0, [1, -1, 2, -1]), np.ones(4), log_probs)
    stitcher.add(batch(2, [-1, -1, 3, -1], start=8), np.ones(4), log_probs)  # batch 1 never came
    stream = stitcher.streams["w0"]
    assert stitcher.discarded == 1  # option 2: its return is unknown
    assert [(d.option, d.done, d.truncated) for d in stream.finished] == [(1, True, True)]
    assert stream.running.option == 3 and stream.running.obs[0] == 10.0
    # workers are stitched separately
    stitcher.add(batch(0, [5, -1], worker="w1"), np.ones(2), log_probs)
    assert stitcher.streams["w1"].running.option == 5 and stitcher.discarded == 1


def test_a_batch_without_options_is_rejected() -> None:
    plain = batch(0, [0, -1])
    with pytest.raises(ProtocolError) as err:
        OptionStitcher(length=1).add(TransitionBatch(**{**plain.__dict__, "option": None}), np.ones(2), log_probs)
    assert err.value.reason == "inconsistent"
