"""Dynamics as a table of rules, and the true local graph each step derives from them.

A :class:`Rule` gives one factor's next value from a few factors' current values. A task is two
sets of rules: *object-state updates* (thawing, soaking, ...), applied every step whatever the
action, and per action the *effects* of its primitive (``goTo(fish)`` moves the agent). Object
states update before the action (Mini-BEHAVIOR's order): both read the state at ``t``, and the
engine checks that no effect reads or writes a factor an update writes, so the order is exact.

The local graph of a step is the but-for dependency of each factor at ``t + 1`` on each factor and
on the action at ``t``: ``s^i_t -> s^j_{t+1}`` when some other value of ``s^i_t`` alone (the
action fixed) changes ``s^j_{t+1}``, and ``a_t -> s^j_{t+1}`` when some other action (the state
fixed) changes it. Changing a non-parent never changes the child, and every edge has a change
that does (the two properties the truth tests check by interventions on the simulator). Self-edges
are always 1. A rule's output and its parents depend only on the values it reads, so both are
computed once per distinct input and kept (the dynamics are deterministic).
"""
from __future__ import annotations

from dataclasses import dataclass
from operator import itemgetter
from typing import Callable, Sequence

import numpy as np

MAX_CACHE_ENTRIES = 250_000
"""Cached rule inputs an engine keeps (about 40 MB) before its caches start over; checked every
``CACHE_CHECK_STEPS`` steps. Bounds memory, not correctness."""
CACHE_CHECK_STEPS = 4096


@dataclass(frozen=True)
class Rule:
    """``child <- fn(*state[reads])``; ``reads[0]`` is the child itself (its current value)."""

    child: int
    reads: tuple[int, ...]
    fn: Callable[..., int]


class _CompiledRule:
    """A rule with its inputs' domains and caches of ``inputs -> (value, flat edge indices)`` (the
    taken action's rules and updates) and ``inputs -> value`` (the other actions' rules)."""

    __slots__ = ("child", "fn", "get", "domains", "columns", "cache", "values")

    def __init__(self, rule: Rule, domains: Sequence[range], width: int) -> None:
        if rule.reads[0] != rule.child or len(set(rule.reads)) != len(rule.reads):
            raise ValueError(f"rule for factor {rule.child} must read it first and each factor once: {rule.reads}")
        self.child, self.fn = rule.child, rule.fn
        reads = rule.reads
        self.get = itemgetter(*reads) if len(reads) > 1 else (lambda s, i=reads[0]: (s[i],))
        self.domains = tuple(domains[i] for i in reads)
        self.columns = tuple(rule.child * width + i for i in reads)
        self.cache: dict[tuple[int, ...], tuple[int, tuple[int, ...]]] = {}
        self.values: dict[tuple[int, ...], int] = {}

    def evaluate(self, state: list[int]) -> tuple[int, tuple[int, ...]]:
        """The child's next value and the flat indices of its non-self parent edges."""
        key = self.get(state)
        hit = self.cache.get(key)
        if hit is None:
            hit = self.cache[key] = self._derive(key)
        return hit

    def value(self, state: list[int]) -> int:
        """The child's next value only."""
        key = self.get(state)
        value = self.values.get(key)
        if value is None:
            value = self.values[key] = self.fn(*key)
        return value

    def cached(self) -> int:
        return len(self.cache) + len(self.values)

    def forget(self) -> None:
        self.cache.clear()
        self.values.clear()

    def _derive(self, key: tuple[int, ...]) -> tuple[int, tuple[int, ...]]:
        fn, domains = self.fn, self.domains
        value = fn(*key)
        parents = []
        alt = list(key)
        for p in range(1, len(key)):
            current = key[p]
            for v in domains[p]:
                if v != current:
                    alt[p] = v
                    if fn(*alt) != value:
                        parents.append(self.columns[p])
                        break
            alt[p] = current
        return value, tuple(parents)


class RuleEngine:
    """Steps a state (a list of ints) under ``updates`` and per-action ``effects``, with local graphs."""

    def __init__(self, domains: Sequence[range], updates: Sequence[Rule], effects: Sequence[Sequence[Rule]]) -> None:
        self.num_factors = d = len(domains)
        self.num_actions = len(effects)
        _check_tables(d, updates, effects)
        self.updates = tuple(_CompiledRule(r, domains, d + 1) for r in updates)
        self.effects = tuple(tuple(_CompiledRule(r, domains, d + 1) for r in rules) for rules in effects)
        self.writable = self._writable()
        self._rules = (*self.updates, *(r for rules in self.effects for r in rules))
        self._steps = 0
        self.eye = np.zeros((d, d + 1), dtype=np.uint8)
        self.eye[np.arange(d), np.arange(d)] = 1

    def _writable(self) -> tuple[tuple[int, tuple[tuple[_CompiledRule, ...], ...], tuple[bool, ...]], ...]:
        """Per factor some action writes: per taken action, the other actions' rules that write it
        and whether some other action leaves it alone."""
        writers: dict[int, list[tuple[int, _CompiledRule]]] = {}
        for a, rules in enumerate(self.effects):
            for rule in rules:
                writers.setdefault(rule.child, []).append((a, rule))
        out = []
        n = self.num_actions
        for j, w in sorted(writers.items()):
            writing = {a for a, _ in w}
            others = tuple(tuple(r for b, r in w if b != a) for a in range(n))
            idle = tuple(n - len(writing) - (a not in writing) > 0 for a in range(n))
            out.append((j, others, idle))
        return tuple(out)

    def step(self, state: list[int], action: int) -> tuple[list[int], list[int]]:
        """The next state and the flat indices (into a ``d x (d + 1)`` graph) of its non-self edges.

        The action is a parent of factor ``j`` when another action gives ``j`` another value: one
        that leaves ``j`` alone (when the taken one changed it) or one whose rule for ``j`` differs.
        """
        self._steps += 1
        if self._steps % CACHE_CHECK_STEPS == 0 and sum(r.cached() for r in self._rules) > MAX_CACHE_ENTRIES:
            for rule in self._rules:
                rule.forget()
        nxt = list(state)
        edges: list[int] = []
        for rule in self.updates:
            nxt[rule.child], parents = rule.evaluate(state)
            edges.extend(parents)
        for rule in self.effects[action]:
            nxt[rule.child], parents = rule.evaluate(state)
            edges.extend(parents)
        width = self.num_factors + 1
        for j, others, idle in self.writable:
            value = nxt[j]
            if value != state[j] and idle[action]:
                edges.append(j * width + width - 1)
                continue
            for rule in others[action]:
                alternative = rule.values.get(rule.get(state))
                if alternative is None:
                    alternative = rule.value(state)
                if alternative != value:
                    edges.append(j * width + width - 1)
                    break
        return nxt, edges

    def graph(self, edges: list[int]) -> np.ndarray:
        """The uint8 ``d x (d + 1)`` local graph with self-edges and ``edges`` set."""
        g = self.eye.copy()
        if edges:
            g.put(edges, 1)
        return g

    def global_graph(self) -> np.ndarray:
        """The union of every rule's reads (and the action for every factor an action writes): each
        is a parent in some state, so this is the union of the local graphs over all states."""
        g = self.eye.copy()
        for rule in self._rules:
            g.put(list(rule.columns), 1)
        width = self.num_factors + 1
        g.put([j * width + width - 1 for j, _, _ in self.writable], 1)
        return g


def _check_tables(d: int, updates: Sequence[Rule], effects: Sequence[Sequence[Rule]]) -> None:
    updated = [r.child for r in updates]
    if len(set(updated)) != len(updated):
        raise ValueError(f"two updates write the same factor: {sorted(updated)}")
    for a, rules in enumerate(effects):
        children = [r.child for r in rules]
        if len(set(children)) != len(children):
            raise ValueError(f"action {a} writes a factor twice: {children}")
        touched = {i for r in rules for i in r.reads}
        if touched & set(updated):
            raise ValueError(f"action {a} reads or writes factors an update writes: {sorted(touched & set(updated))}")
    if any(not 0 <= i < d for r in (*updates, *(r for rs in effects for r in rs)) for i in r.reads):
        raise ValueError(f"a rule reads a factor outside [0, {d - 1}]")
