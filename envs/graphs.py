"""Object-level causal DAGs for the Chemical environment (dissertation chapter 3.3.1).

An :class:`ObjectDAG` says which objects' colours feed which objects' conditional probability
tables: an edge ``(parent, child)`` means the child's colour is re-sampled from a table that reads
the parent's colour. This is the *object* graph; the one-step factor graph a learner should recover
is derived from it in :mod:`envs.chemical_truth` and differs from it.

Graphs come from the named constructors (:func:`collider`, :func:`chain`, :func:`full`), from
:func:`random_dag`, or from a JSON file ``{"num_objects": 10, "edges": [[0, 3], [1, 3]]}`` read by
:func:`load_dag`. Every malformed graph raises :class:`GraphSpecError` naming the problem.
"""
from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Callable

import numpy as np

NAMED_GRAPHS = ("collider", "chain", "full")
_JSON_KEYS = {"num_objects", "edges", "description"}


class GraphSpecError(ValueError):
    """A graph specification (name, JSON file or edge list) is malformed."""


@dataclass(frozen=True)
class ObjectDAG:
    """A directed acyclic graph over objects ``0 .. num_objects - 1``; edges are (parent, child).

    Construction validates everything and stores the edges sorted, so equal graphs compare equal.
    """

    num_objects: int
    edges: tuple[tuple[int, int], ...]

    def __post_init__(self) -> None:
        _check_num_objects(self.num_objects)
        if not isinstance(self.edges, (list, tuple)):
            raise GraphSpecError(f"edges must be a sequence of (parent, child) pairs, got {type(self.edges).__name__}")
        edges = tuple(_check_edge(e, self.num_objects) for e in self.edges)
        _check_no_duplicates(edges)
        edges = tuple(sorted(edges))
        object.__setattr__(self, "edges", edges)
        cycle = _find_cycle(self.num_objects, edges)
        if cycle:
            raise GraphSpecError("edges contain a cycle: " + " -> ".join(map(str, cycle)))

    def parents(self, k: int) -> tuple[int, ...]:
        """The parents of object ``k``, ascending."""
        return self._parents[k]

    def children(self, k: int) -> tuple[int, ...]:
        """The children of object ``k``, ascending."""
        return self._children[k]

    def descendants(self, k: int) -> frozenset[int]:
        """Every object reachable from ``k`` by a directed path, ``k`` itself excluded."""
        return self._reachable(k, self.children)

    def ancestors(self, k: int) -> frozenset[int]:
        """Every object with a directed path to ``k``, ``k`` itself excluded."""
        return self._reachable(k, self.parents)

    def topological_order(self) -> tuple[int, ...]:
        """Kahn's algorithm, always taking the smallest ready index first (so it is unique)."""
        return self._topological_order

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready form read back by :func:`load_dag`."""
        return {"num_objects": self.num_objects, "edges": [list(e) for e in self.edges]}

    def to_json(self) -> str:
        """This graph as the JSON text :func:`load_dag` reads."""
        return json.dumps(self.to_dict())

    @cached_property
    def _parents(self) -> tuple[tuple[int, ...], ...]:
        return tuple(tuple(sorted(p for p, c in self.edges if c == k)) for k in range(self.num_objects))

    @cached_property
    def _children(self) -> tuple[tuple[int, ...], ...]:
        return tuple(tuple(sorted(c for p, c in self.edges if p == k)) for k in range(self.num_objects))

    @cached_property
    def _topological_order(self) -> tuple[int, ...]:
        indegree = [len(self.parents(k)) for k in range(self.num_objects)]
        ready = [k for k in range(self.num_objects) if indegree[k] == 0]
        order: list[int] = []
        while ready:
            k = min(ready)
            ready.remove(k)
            order.append(k)
            for c in self.children(k):
                indegree[c] -= 1
                if indegree[c] == 0:
                    ready.append(c)
        return tuple(order)

    def _reachable(self, k: int, step: Callable[[int], tuple[int, ...]]) -> frozenset[int]:
        seen: set[int] = set()
        frontier = deque(step(k))
        while frontier:
            node = frontier.popleft()
            if node not in seen:
                seen.add(node)
                frontier.extend(step(node))
        return frozenset(seen)


def collider(n: int) -> ObjectDAG:
    """Objects ``0 .. n-2`` are all parents of object ``n-1``."""
    _check_num_objects(n)
    return ObjectDAG(n, tuple((k, n - 1) for k in range(n - 1)))


def chain(n: int) -> ObjectDAG:
    """``0 -> 1 -> ... -> n-1``."""
    _check_num_objects(n)
    return ObjectDAG(n, tuple((k, k + 1) for k in range(n - 1)))


def full(n: int) -> ObjectDAG:
    """The complete DAG: ``i -> j`` for every ``i < j``."""
    _check_num_objects(n)
    return ObjectDAG(n, tuple((i, j) for i in range(n) for j in range(i + 1, n)))


def random_dag(num_objects: int, num_edges: int, seed: int) -> ObjectDAG:
    """``num_edges`` distinct edges drawn uniformly, consistent with a random order of the objects.

    The order is a random permutation, so object indices are generally *not* a topological order.
    """
    _check_num_objects(num_objects)
    max_edges = num_objects * (num_objects - 1) // 2
    if not 0 <= num_edges <= max_edges:
        raise GraphSpecError(f"num_edges must be in [0, {max_edges}] for {num_objects} objects, got {num_edges}")
    rng = np.random.default_rng(seed)
    order = rng.permutation(num_objects)
    pairs = [(int(order[a]), int(order[b])) for a in range(num_objects) for b in range(a + 1, num_objects)]
    chosen = rng.choice(len(pairs), size=num_edges, replace=False)
    return ObjectDAG(num_objects, tuple(sorted(pairs[i] for i in chosen)))


_CONSTRUCTORS: dict[str, Callable[[int], ObjectDAG]] = {"collider": collider, "chain": chain, "full": full}


def load_dag(spec: str | Path, num_objects: int) -> ObjectDAG:
    """A named graph (``"collider"``, ``"chain"``, ``"full"``) on ``num_objects``, or a JSON file.

    The file holds ``{"num_objects": N, "edges": [[parent, child], ...]}`` (and optionally a
    ``"description"``); its ``num_objects``, when present, wins over the argument.
    """
    if isinstance(spec, str) and spec in _CONSTRUCTORS:
        return _CONSTRUCTORS[spec](num_objects)
    path = Path(spec)
    if not path.is_file():
        raise GraphSpecError(f"graph file not found: {path} (or use one of {', '.join(NAMED_GRAPHS)})")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise GraphSpecError(f"invalid JSON in graph file {path}: {err}") from err
    try:
        return dag_from_dict(data, num_objects)
    except GraphSpecError as err:
        raise GraphSpecError(f"{path}: {err}") from err


def dag_from_dict(data: Any, num_objects: int) -> ObjectDAG:
    """Validate the parsed JSON form of a graph; ``data["num_objects"]`` wins over the argument."""
    if not isinstance(data, dict):
        raise GraphSpecError(f"graph must be a JSON object with key 'edges', got {type(data).__name__}")
    unknown = sorted(set(data) - _JSON_KEYS)
    if unknown:
        raise GraphSpecError(f"unknown keys {unknown}; allowed: {sorted(_JSON_KEYS)}")
    if "edges" not in data:
        raise GraphSpecError("missing key 'edges'")
    edges = data["edges"]
    if not isinstance(edges, list):
        raise GraphSpecError(f"'edges' must be a list of [parent, child] pairs, got {type(edges).__name__}")
    return ObjectDAG(data.get("num_objects", num_objects), tuple(edges))


def _is_int(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _check_num_objects(n: Any) -> None:
    if not _is_int(n):
        raise GraphSpecError(f"num_objects must be an int, got {n!r}")
    if n < 1:
        raise GraphSpecError(f"num_objects must be >= 1, got {n}")


def _check_edge(edge: Any, n: int) -> tuple[int, int]:
    if not isinstance(edge, (list, tuple)) or len(edge) != 2:
        raise GraphSpecError(f"edge {edge!r} must be a [parent, child] pair")
    if not all(_is_int(x) for x in edge):
        raise GraphSpecError(f"edge {list(edge)!r} has a non-int object id")
    parent, child = int(edge[0]), int(edge[1])
    for x in (parent, child):
        if not 0 <= x < n:
            raise GraphSpecError(f"edge {[parent, child]} has object id {x} out of range [0, {n - 1}]")
    if parent == child:
        raise GraphSpecError(f"edge {[parent, child]} is a self-loop")
    return parent, child


def _check_no_duplicates(edges: tuple[tuple[int, int], ...]) -> None:
    seen: set[tuple[int, int]] = set()
    for e in edges:
        if e in seen:
            raise GraphSpecError(f"duplicate edge {list(e)}")
        seen.add(e)


def _find_cycle(n: int, edges: tuple[tuple[int, int], ...]) -> list[int]:
    """One directed cycle as ``[a, b, ..., a]``, or ``[]`` when the graph is acyclic."""
    children: list[list[int]] = [[] for _ in range(n)]
    for p, c in edges:
        children[p].append(c)
    state = [0] * n  # 0 unvisited, 1 on the current path, 2 done
    for root in range(n):
        if state[root]:
            continue
        path, stack = [root], [iter(children[root])]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state[nxt] == 1:
                return path[path.index(nxt):] + [nxt]
            elif state[nxt] == 0:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(children[nxt]))
    return []
