"""``RunObserver``: what a run's liveliness tokens and stats beats say, watched over a window.

Tokens are the truth about who is alive (the router drops a token within milliseconds of its
holder's death); beats carry each instance's counters once a second. A snapshot joins both, and
keeps the token changes seen while watching, so an instance that died (and perhaps came back) during
the window can be told apart from one that was steady.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from proto import topics
from proto.codec import ProtocolError, decode
from proto.messages import ServiceStats
from services.bus.base import Handle, Transport

Instance = tuple[str, str]
"""(service, instance)."""

MAX_BEATS = 32
"""Beats kept per instance: a few seconds' worth, enough for a rate."""


@dataclass(frozen=True)
class TokenChange:
    """A liveliness token appearing (``alive``) or disappearing, at wall-clock time ``at``."""

    instance: Instance
    alive: bool
    at: float


@dataclass(frozen=True)
class Observation:
    """A run as watched from ``started`` to ``ended`` (wall-clock seconds)."""

    started: float
    ended: float
    alive: frozenset[Instance]
    """Instances whose token was alive at ``ended``."""
    changes: tuple[TokenChange, ...]
    """Every token change reported, the initial "alive now" reports first."""
    beats: dict[Instance, tuple[ServiceStats, ...]] = field(default_factory=dict)
    """Stats beats received, oldest first, per instance."""
    rejected: int = 0
    """Payloads on the stats topic that failed validation."""

    def instances(self) -> list[Instance]:
        """Every instance that holds a token, lost one, or beat, sorted."""
        return sorted(self.alive | {c.instance for c in self.changes} | set(self.beats))

    def changes_of(self, instance: Instance) -> list[TokenChange]:
        return [c for c in self.changes if c.instance == instance]


class RunObserver:
    """Watches the tokens and beats of one run (optionally one service) until ``close``.

    The transport's callbacks only append under a lock; ``wait_until`` and ``snapshot`` read.
    """

    def __init__(self, bus: Transport, run_id: str, service: str = "*", beats: bool = True) -> None:
        self.started = time.time()
        self._condition = threading.Condition()
        self._alive: set[Instance] = set()
        self._changes: list[TokenChange] = []
        self._beats: dict[Instance, list[ServiceStats]] = {}
        self._rejected = 0
        self._handles: list[Handle] = [bus.watch_liveliness(topics.alive(run_id, service), self._on_token)]
        if beats:
            self._handles.append(bus.subscribe(topics.stats(run_id, service), self._on_beat))

    def _on_token(self, key: str, alive: bool) -> None:
        _, service, instance = topics.parse_alive(key)
        with self._condition:
            (self._alive.add if alive else self._alive.discard)((service, instance))
            self._changes.append(TokenChange((service, instance), alive, time.time()))
            self._condition.notify_all()

    def _on_beat(self, key: str, payload: bytes) -> None:
        try:
            stats = decode(payload, ServiceStats)
        except ProtocolError:
            with self._condition:
                self._rejected += 1
            return
        with self._condition:
            kept = self._beats.setdefault((stats.service, stats.instance), [])
            kept.append(stats)
            del kept[:-MAX_BEATS]
            self._condition.notify_all()

    def alive(self, service: str | None = None) -> list[Instance]:
        """Instances alive now (of ``service``, when given), sorted."""
        with self._condition:
            return sorted(i for i in self._alive if service is None or i[0] == service)

    def wait_until(self, predicate: Callable[[RunObserver], bool], timeout: float) -> bool:
        """Wait until ``predicate(self)`` holds (re-checked on every token or beat); False on timeout."""
        deadline = time.monotonic() + timeout
        with self._condition:
            while not predicate(self):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._condition.wait(min(left, 0.1))
        return True

    def snapshot(self) -> Observation:
        with self._condition:
            return Observation(self.started, time.time(), frozenset(self._alive), tuple(self._changes),
                               {i: tuple(b) for i, b in self._beats.items()}, self._rejected)

    def close(self) -> None:
        for handle in reversed(self._handles):
            handle.close()

    def __enter__(self) -> RunObserver:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def observe(bus: Transport, run_id: str, seconds: float) -> Observation:
    """Watch every service of ``run_id`` for ``seconds`` (two beats at the default 1 s interval)."""
    with RunObserver(bus, run_id) as observer:
        time.sleep(seconds)
        return observer.snapshot()
