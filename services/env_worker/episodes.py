"""Task performance of an env-worker's episodes: return, success and stages, over a recent window.

Reported in the worker's stats beat (``return_mean``, ``success_rate``, ``stages_mean``) and from
there in the run summary's ``task`` block. ``success_rate`` needs an env that says when its task is
done (``info["success"]``: the household tasks, 2D Minecraft); ``stages_mean`` one that reports the
stages reached (``info["num_stages"]``) out of its ``stage_names``: chapter 5's normalised stage count.
"""
from __future__ import annotations

from collections import deque
from typing import Any


class EpisodeStats:
    """The last ``window`` finished episodes' return, success and fraction of stages reached."""

    def __init__(self, num_stages: int, window: int = 100) -> None:
        self.num_stages = num_stages
        self.returns: deque[float] = deque(maxlen=window)
        self.successes: deque[float] = deque(maxlen=window)
        self.stages: deque[float] = deque(maxlen=window)
        self.episode_return = 0.0
        self.finished = 0

    def step(self, reward: float, info: dict[str, Any], done: bool) -> None:
        self.episode_return += float(reward)
        if not done:
            return
        self.returns.append(self.episode_return)
        if "success" in info:
            self.successes.append(float(bool(info["success"])))
        if "num_stages" in info and self.num_stages:
            self.stages.append(min(info["num_stages"] / self.num_stages, 1.0))
        self.episode_return = 0.0
        self.finished += 1

    def values(self) -> dict[str, float]:
        """The window's means (only those the env provides)."""
        out = {}
        for name, values in (("return_mean", self.returns), ("success_rate", self.successes),
                             ("stages_mean", self.stages)):
            if values:
                out[name] = sum(values) / len(values)
        return out
