"""Ground-truth graphs of the Chemical environment, derived from what its dynamics do.

Factor layout: object ``k`` owns factors ``3k`` (colour), ``3k + 1`` (x) and ``3k + 2`` (y); a graph
is a uint8 ``[3N, 3N + 1]`` matrix, row = factor at t+1, column = factor at t, last column the action.

The one-step graph is *not* the object DAG (see :func:`one_step_color_dependencies`): learners are
scored against the graphs built here.
"""
from __future__ import annotations

import numpy as np

from envs.graphs import ObjectDAG

FACTORS_PER_OBJECT = 3
"""colour, x, y"""


def color_factor(k: int) -> int:
    """Index of object ``k``'s colour factor."""
    return FACTORS_PER_OBJECT * k


def intervention_color_dependencies(dag: ObjectDAG, target: int) -> set[tuple[int, int]]:
    """Pairs ``(m, j)``, ``m != j``: after an action on ``target``, colour_j(t+1) reads colour_m(t).

    The action sets ``target``'s colour; each descendant is then re-sampled, in topological order,
    from its parents' newest colours. Following the computation backwards from a re-sampled ``j``:
    its new value is a function of its parents' new values, where a parent that is ``target`` or
    was itself re-sampled contributes its *new* value (computed from its own parents in the same
    way) and any other parent contributes its *old* value. So the old colours it reads are exactly
    those of the parents ``m`` of a re-sampled ``r`` on some path ``r -> ... -> j`` (every node of
    which is re-sampled, being a descendant of ``r``), with ``m`` neither ``target`` nor
    re-sampled. Objects outside ``descendants(target) | {target}`` keep their colour and read only
    themselves.
    """
    resampled = dag.descendants(target)
    overwritten = resampled | {target}
    deps: set[tuple[int, int]] = set()
    for j in resampled:
        for r in (dag.ancestors(j) | {j}) & resampled:
            deps.update((m, j) for m in dag.parents(r) if m not in overwritten)
    return deps


def one_step_color_dependencies(dag: ObjectDAG) -> set[tuple[int, int]]:
    """Pairs ``(m, j)``, ``m != j``: colour_j at t+1 depends on colour_m at t (the global truth).

    colour_j(t+1) depends on colour_m(t) iff some action reveals it, i.e. there is an intervention
    target ``i`` with ``j`` in ``descendants(i)`` and a re-sampled ``r`` in
    ``({j} | ancestors(j)) & descendants(i)`` having ``m`` as a parent, ``m`` not in
    ``descendants(i) | {i}`` (derivation in :func:`intervention_color_dependencies`; this is the
    union over targets). Consequences:

    * an object's *only* parent is never such an ``m``: when the child is re-sampled, either the
      action set it directly (the old parent colour is unused) or the parent was intervened on or
      re-sampled first (its old colour is overwritten). A chain has no cross-object edges;
    * full(n) keeps ``m -> j`` iff ``m <= j - 2`` (intervene on some ``i`` strictly between);
      a collider keeps all its edges (n >= 3: intervene on another parent);
    * a non-parent ancestor ``m`` can appear: intervening on ``i`` re-samples ``r`` from old
      ``m``, and ``j`` below ``r`` inherits that dependence.

    The edges hold for generic tables (faithfulness); a table that ignores one of its inputs would
    remove some.
    """
    deps: set[tuple[int, int]] = set()
    for target in range(dag.num_objects):
        deps |= intervention_color_dependencies(dag, target)
    return deps


def _graph_with_self_edges(num_objects: int) -> np.ndarray:
    d = FACTORS_PER_OBJECT * num_objects
    graph = np.zeros((d, d + 1), dtype=np.uint8)
    graph[np.arange(d), np.arange(d)] = 1
    return graph


def _add_color_edges(graph: np.ndarray, deps: set[tuple[int, int]]) -> None:
    for m, j in deps:
        graph[color_factor(j), color_factor(m)] = 1


def global_graph(dag: ObjectDAG) -> np.ndarray:
    """The one-step ground truth: self-edges (Assumption 4), the action into every colour, and the
    colour-to-colour edges of :func:`one_step_color_dependencies`; positions read nothing else."""
    graph = _graph_with_self_edges(dag.num_objects)
    colors = [color_factor(k) for k in range(dag.num_objects)]
    graph[colors, -1] = 1
    _add_color_edges(graph, one_step_color_dependencies(dag))
    return graph


def local_graph(dag: ObjectDAG, target: int) -> np.ndarray:
    """The graph of one transition whose action targets ``target``: self-edges, the action into the
    target's and every re-sampled colour, and the old colours each re-sampled colour was computed
    from (:func:`intervention_color_dependencies`). It depends on the target only."""
    graph = _graph_with_self_edges(dag.num_objects)
    touched = [color_factor(k) for k in sorted(dag.descendants(target) | {target})]
    graph[touched, -1] = 1
    _add_color_edges(graph, intervention_color_dependencies(dag, target))
    return graph
