"""Definitions 3.1-3.3 on the example graph of Fig. 3.2."""
from __future__ import annotations

import numpy as np

from causal.abstraction import cdl_abstraction


def graph(n: int, edges: list[tuple[int, int]], action_children: list[int]) -> np.ndarray:
    g = np.eye(n, n + 1, dtype=np.uint8)
    for cause, effect in edges:
        g[effect, cause] = 1
    for j in action_children:
        g[j, n] = 1
    return g


def test_controllable_action_relevant_irrelevant() -> None:
    # 0 <- action; 1 <- 0 (descendant over time); 2 -> 0 (ancestor of a controllable); 3 -> 2 (ancestor too);
    # 4 <- 2 only (irrelevant: neither a descendant of the action nor an ancestor of a controllable)
    g = graph(5, [(0, 1), (2, 0), (3, 2), (2, 4)], action_children=[0])
    a = cdl_abstraction(g)
    assert a.controllable == (0, 1)
    assert a.action_relevant == (2, 3)
    assert a.action_irrelevant == (4,)
    assert a.kept == (0, 1, 2, 3)
    assert a.named(["a", "b", "c", "d", "e"])["action_irrelevant"] == ["e"]


def test_no_action_edges_means_nothing_controllable() -> None:
    a = cdl_abstraction(graph(3, [(0, 1)], action_children=[]))
    assert a.controllable == () and a.action_relevant == () and a.action_irrelevant == (0, 1, 2)
