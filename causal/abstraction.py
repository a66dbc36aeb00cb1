"""CDL's task-independent state abstraction (Definitions 3.1-3.3 of the dissertation).

The graph is ``d_S x (d_S + 1)``: entry [j, i] = 1 when S^i_t -> S^j_{t+1}, the action is column d_S.
Ancestors and descendants are taken over time, so they are reachability in this graph.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Abstraction:
    """The three classes of state factors and the abstraction phi(S) = (S^C, S^AR)."""

    controllable: tuple[int, ...]
    action_relevant: tuple[int, ...]
    action_irrelevant: tuple[int, ...]

    @property
    def kept(self) -> tuple[int, ...]:
        return tuple(sorted(self.controllable + self.action_relevant))

    def named(self, names: tuple[str, ...] | list[str]) -> dict[str, list[str]]:
        return {cls: [names[i] for i in getattr(self, cls)]
                for cls in ("controllable", "action_relevant", "action_irrelevant")}


def with_self_edges(adjacency: np.ndarray) -> np.ndarray:
    """Assumption 4 of ch. 3: every factor depends on itself, whatever the estimate says."""
    out = np.asarray(adjacency, dtype=bool).copy()
    n = out.shape[0]
    out[np.arange(n), np.arange(n)] = True
    return out


def _reach(start: set[int], step: dict[int, set[int]]) -> set[int]:
    seen, frontier = set(start), list(start)
    while frontier:
        for nxt in step.get(frontier.pop(), ()):
            if nxt not in seen:
                seen.add(nxt)
                frontier.append(nxt)
    return seen


def cdl_abstraction(adjacency: np.ndarray) -> Abstraction:
    """Controllable = descendants of the action; action-relevant = their other ancestors; the rest irrelevant."""
    adj = np.asarray(adjacency, dtype=bool)
    n = adj.shape[0]
    children = {i: {j for j in range(n) if adj[j, i] and j != i} for i in range(n)}
    parents = {j: {i for i in range(n) if adj[j, i] and i != j} for j in range(n)}
    controllable = _reach({j for j in range(n) if adj[j, n]}, children)
    relevant = _reach(controllable, parents) - controllable
    irrelevant = set(range(n)) - controllable - relevant
    return Abstraction(tuple(sorted(controllable)), tuple(sorted(relevant)), tuple(sorted(irrelevant)))


def reward_ancestors(adjacency: np.ndarray, reward_parents: np.ndarray) -> set[int]:
    """AN(R) of Theorem 4.1: the state factors among the reward's parents (``[d_S + 1]``, action last)
    and every factor that reaches one of them through the dynamics graph (breadth-first over parents)."""
    adj = np.asarray(adjacency, dtype=bool)
    n = adj.shape[0]
    parents = {j: {i for i in range(n) if adj[j, i] and i != j} for j in range(n)}
    start = {i for i in range(n) if reward_parents[i]}
    return _reach(start, parents)


def minimal_abstraction(adjacency: np.ndarray, reward_parents: np.ndarray | None = None) -> Abstraction:
    """CBM's task abstraction (Theorem 4.1): keep AN(R), the reward's parents and their ancestors in the
    dynamics graph; drop the rest. In CDL's three classes: the kept factors the action reaches are
    ``controllable``, the other kept ones ``action_relevant`` (a reward parent the action cannot move,
    like chapter 4's sun, is kept there), and every dropped factor ``action_irrelevant``, so
    ``Abstraction.kept`` is AN(R). Without reward parents (a method that learns none) it is CDL's."""
    if reward_parents is None:
        return cdl_abstraction(adjacency)
    kept = reward_ancestors(adjacency, reward_parents)
    reached = set(cdl_abstraction(adjacency).controllable)
    n = np.asarray(adjacency).shape[0]
    return Abstraction(tuple(sorted(kept & reached)), tuple(sorted(kept - reached)),
                       tuple(sorted(set(range(n)) - kept)))


def abstraction_accuracy(kept: tuple[int, ...] | set[int], true_kept: tuple[int, ...] | set[int],
                         num_factors: int) -> float:
    """Share of state factors an abstraction classifies as the true one does (kept or dropped): the
    chapter's "# correctly classified state factors / total state factors"."""
    kept, true_kept = set(kept), set(true_kept)
    return sum((j in kept) == (j in true_kept) for j in range(num_factors)) / max(num_factors, 1)
