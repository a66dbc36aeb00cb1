"""dashboard cells: how one graph's entries reach the page, shared by global and local graphs.

Rows are factors at t+1, columns factors at t with the action last; the diagonal (self-edges) is
always present and never scored.
"""
from __future__ import annotations

import numpy as np

from causal.graph_metrics import scored_entries

ACTION_COLUMN = "action"
OUTCOMES = ("tp", "fp", "fn", "tn")


def cause_names(factor_names: tuple[str, ...] | list[str]) -> list[str]:
    """Column labels: the factors at t, then the action."""
    return list(factor_names) + [ACTION_COLUMN]


def classify(learned: np.ndarray, truth: np.ndarray | None) -> list[list[str | None]]:
    """Per cell: "tp", "fp", "fn", "tn"; "self" on the diagonal (never scored); None without a truth."""
    rows, cols = learned.shape
    if truth is None:
        return [["self" if i == j else None for j in range(cols)] for i in range(rows)]
    scored = scored_entries(learned.shape)
    p, t = learned.astype(bool), truth.astype(bool)
    names = np.where(p, np.where(t, "tp", "fp"), np.where(t, "fn", "tn"))
    return [[str(names[i, j]) if scored[i, j] else "self" for j in range(cols)] for i in range(rows)]


def count_outcomes(outcome: list[list[str | None]]) -> dict[str, int]:
    """How many cells of each scored outcome."""
    return {o: sum(row.count(o) for row in outcome) for o in OUTCOMES}


def short(value: float) -> float:
    """Five significant digits: enough for a tooltip, a third of the JSON."""
    return float(f"{float(value):.5g}")
