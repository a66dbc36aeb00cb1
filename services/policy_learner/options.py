"""Decisions of a policy over skills, stitched from step-level transition batches. Pure (no bus).

The chapter collects manipulation data with PPO whose action space is long-horizon skills (3.3.1,
following Nasiriany et al.), while dynamics learning sees the raw motor actions. Env-workers publish
the motor steps, with ``TransitionBatch.option`` marking the steps where the policy picked a skill.
A *decision* is one skill execution as one step of a semi-MDP: the observation where the skill was
picked, the option, its behaviour log-probability, the **sum** of the step rewards until the next
decision or the episode's end, and the observation after it. The discount applies once per decision
(not per motor step): a skill is one step of the policy's MDP.

Skills run across batch boundaries, so decisions are stitched per worker in ``seq`` order. A gap
(a batch lost or dropped for its policy lag) leaves the running decision's return unknown: it is
discarded, and the decision before it ends its GAE chain there (``done``, value-bootstrapped as a
truncation), since the next stitched decision does not follow it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from proto.codec import ProtocolError
from proto.messages import TransitionBatch


@dataclass
class Decision:
    obs: np.ndarray
    option: int
    log_prob: float
    reward: float = 0.0
    steps: int = 0
    next_obs: np.ndarray | None = None
    done: bool = False
    truncated: bool = False
    """The decision's episode went on (a time limit or a gap): its value is bootstrapped."""


@dataclass
class _Stream:
    seq: int | None = None
    running: Decision | None = None
    finished: list[Decision] = field(default_factory=list)


LogProbs = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``(observations [K, d], options [K]) -> behaviour log-probabilities [K]``."""


class OptionStitcher:
    """Turns each worker's batches into runs of ``length`` consecutive finished decisions."""

    def __init__(self, length: int) -> None:
        if length < 1:
            raise ValueError("decisions per segment must be >= 1")
        self.length = length
        self.streams: dict[str, _Stream] = {}
        self.decisions = 0
        self.discarded = 0
        """Decisions whose return was lost in a gap."""
        self.returns: dict[int, tuple[int, float]] = {}
        """Per option: (finished decisions, sum of their returns): what the reward pays for each skill."""

    def add(self, batch: TransitionBatch, reward: np.ndarray, log_probs: LogProbs) -> list[list[Decision]]:
        """Stitch ``batch`` (its per-step ``reward`` already weighted) and return the runs it completes.

        Raises ProtocolError('inconsistent') for a batch without options."""
        if batch.option is None:
            raise ProtocolError("inconsistent", f"TransitionBatch {batch.worker_id}/{batch.seq} has no skill options "
                                                "for a policy over skills")
        stream = self.streams.setdefault(batch.worker_id, _Stream())
        if stream.seq is not None and batch.seq != stream.seq + 1:
            self._gap(stream)
        stream.seq = batch.seq
        starts = np.flatnonzero(batch.option >= 0)
        picked = log_probs(batch.state[starts], batch.option[starts]) if len(starts) else np.zeros(0)
        logp = dict(zip(starts.tolist(), picked.tolist()))
        ended = batch.terminated | batch.truncated
        for t in range(len(batch)):
            if t in logp:
                if stream.running is not None:
                    self._finish(stream, batch.state[t], done=False, truncated=False)
                stream.running = Decision(batch.state[t].copy(), int(batch.option[t]), logp[t])
            running = stream.running
            if running is None:
                continue  # the tail of a skill whose start was not seen
            running.reward += float(reward[t])
            running.steps += 1
            if ended[t]:
                self._finish(stream, batch.next_state[t], done=True,
                             truncated=bool(batch.truncated[t] and not batch.terminated[t]))
        runs = []
        while len(stream.finished) >= self.length:
            runs.append(stream.finished[: self.length])
            stream.finished = stream.finished[self.length:]
        return runs

    def _finish(self, stream: _Stream, next_obs: np.ndarray, *, done: bool, truncated: bool) -> None:
        decision = stream.running
        decision.next_obs, decision.done, decision.truncated = next_obs.copy(), done, truncated
        stream.finished.append(decision)
        stream.running = None
        self.decisions += 1
        count, total = self.returns.get(decision.option, (0, 0.0))
        self.returns[decision.option] = (count + 1, total + decision.reward)

    def mean_returns(self) -> dict[int, float]:
        """Mean return of the finished decisions of each option so far."""
        return {option: total / count for option, (count, total) in sorted(self.returns.items())}

    def _gap(self, stream: _Stream) -> None:
        if stream.running is not None:
            self.discarded += 1
            stream.running = None
        if stream.finished and not stream.finished[-1].done:
            stream.finished[-1].done = stream.finished[-1].truncated = True
