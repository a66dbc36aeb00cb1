"""Ground truth of a task's reward: which factors at t (and the action) it depends on.

Causeway's graphs read ``(s_t, a_t)`` (the last column the action), and chapter 4's causal reward
model is ``R(S_t, A_t)``. Gymnasium environments compute ``r_t`` on the state the step reached, so a
reward that is a function of some factors at t+1 depends, through one step of the dynamics, on
exactly their parents at t (their self-edges included), and on the action if any of them does.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np


def parents_through_step(graph: np.ndarray, factors: Sequence[int]) -> np.ndarray:
    """uint8 ``[d + 1]``: the ``(s_t, a_t)`` parents of a reward computed from ``factors`` at t+1,
    given the true one-step graph ``[d, d + 1]`` (row = factor at t+1, action last)."""
    rows = np.asarray(graph)[list(factors)]
    return rows.any(axis=0).astype(np.uint8) if len(rows) else np.zeros(graph.shape[1], np.uint8)
