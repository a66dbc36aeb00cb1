"""The whole bus in one process: several ``InMemoryTransport`` objects share one ``InMemoryBus`` hub.

Semantics follow ``ZenohTransport`` so a pipeline tested here behaves the same over Zenoh:

- key expressions are ``/``-separated chunks where ``*`` matches exactly one chunk and ``**`` any
  number of chunks (zero included), as in Zenoh; two expressions match when they intersect;
- callbacks run synchronously on the publishing thread, one at a time per subscriber (Zenoh too never
  runs one subscriber's callback concurrently with itself); an exception in a callback is logged
  and swallowed, as Zenoh does, so a faulty subscriber never breaks its publisher;
- ``query`` returns the set values of every ``serve_latest`` whose key intersects the expression;
- liveliness counts tokens per key: watchers see ``True`` when the first token on a key appears
  and ``False`` when the last one goes; closing a transport closes everything it declared, which is
  how tests simulate a crashed service.

Callbacks are always invoked without the hub lock held, so a callback may publish, declare or close.
One caveat of synchronous delivery: two threads whose callbacks publish into each other's
subscribers, each blocking on the other, deadlock here where Zenoh (a thread per subscriber)
would not; callbacks should hand off to a queue and return, as ``base.Callback`` asks anyway.
"""
from __future__ import annotations

import functools
import logging
import threading
from collections import Counter
from typing import Any, Callable

from services.bus.handles import HandleRegistry
from services.bus.base import Callback, Handle, LatestValue, LivelinessCallback

logger = logging.getLogger(__name__)


def validate_key_expr(key_expr: str) -> tuple[str, ...]:
    """Split ``key_expr`` into chunks; raise ``ValueError`` for empty chunks or stray slashes."""
    chunks = tuple(key_expr.split("/"))
    if not key_expr or any(not chunk for chunk in chunks):
        raise ValueError(f"invalid key expression {key_expr!r}: empty chunk")
    return chunks


@functools.lru_cache(maxsize=4096)
def key_intersects(a: str, b: str) -> bool:
    """True when some concrete key matches both key expressions ``a`` and ``b``."""
    return _chunks_intersect(validate_key_expr(a), validate_key_expr(b))


@functools.lru_cache(maxsize=4096)
def _chunks_intersect(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    if not a or not b:
        return all(chunk == "**" for chunk in a + b)
    if a[0] == "**":
        return _chunks_intersect(a[1:], b) or _chunks_intersect(a, b[1:])
    if b[0] == "**":
        return _chunks_intersect(a, b[1:]) or _chunks_intersect(a[1:], b)
    heads_match = a[0] == b[0] or "*" in (a[0], b[0])
    return heads_match and _chunks_intersect(a[1:], b[1:])


class _Delivery:
    """One callback behind its own lock: serial delivery, nothing delivered once closed."""

    def __init__(self, key_expr: str, callback: Callable[..., None]) -> None:
        self.key_expr = key_expr
        self._callback = callback
        self._lock = threading.RLock()
        self._closed = False

    def deliver(self, *args: Any) -> None:
        with self._lock:
            if self._closed:
                return
            try:
                self._callback(*args)
            except Exception:
                logger.exception("bus callback on %r raised; message dropped", self.key_expr)

    def hold(self) -> threading.RLock:
        """The delivery lock, for a caller that must deliver a sequence before anyone else."""
        return self._lock

    def close(self) -> None:
        self._closed = True


class InMemoryBus:
    """The hub: every subscriber, queryable and liveliness token of the transports attached to it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscribers: set[_Delivery] = set()
        self._watchers: set[_Delivery] = set()
        self._latest: set[_MemoryLatest] = set()
        self._tokens: Counter[str] = Counter()

    def publish(self, key: str, payload: bytes) -> None:
        validate_key_expr(key)
        with self._lock:
            targets = [s for s in self._subscribers if key_intersects(s.key_expr, key)]
        for subscriber in targets:
            subscriber.deliver(key, payload)

    def add_subscriber(self, delivery: _Delivery) -> None:
        validate_key_expr(delivery.key_expr)
        with self._lock:
            self._subscribers.add(delivery)

    def remove_subscriber(self, delivery: _Delivery) -> None:
        delivery.close()
        with self._lock:
            self._subscribers.discard(delivery)

    def add_latest(self, latest: _MemoryLatest) -> None:
        with self._lock:
            self._latest.add(latest)

    def remove_latest(self, latest: _MemoryLatest) -> None:
        with self._lock:
            self._latest.discard(latest)

    def query(self, key_expr: str) -> list[tuple[str, bytes]]:
        validate_key_expr(key_expr)
        with self._lock:
            served = [q for q in self._latest if key_intersects(q.key, key_expr)]
        replies = [(q.key, q.value) for q in served]
        return sorted((key, value) for key, value in replies if value is not None)

    def declare_token(self, key: str) -> None:
        validate_key_expr(key)
        with self._lock:
            self._tokens[key] += 1
            first = self._tokens[key] == 1
        if first:
            self._notify(key, True)

    def undeclare_token(self, key: str) -> None:
        with self._lock:
            self._tokens[key] -= 1
            last = self._tokens[key] == 0
            if last:
                del self._tokens[key]
        if last:
            self._notify(key, False)

    def alive(self, key_expr: str) -> list[str]:
        validate_key_expr(key_expr)
        with self._lock:
            return sorted(key for key in self._tokens if key_intersects(key, key_expr))

    def add_watcher(self, watcher: _Delivery) -> None:
        """Register ``watcher`` and report the tokens alive now before any later change."""
        validate_key_expr(watcher.key_expr)
        with self._lock:
            self._watchers.add(watcher)
            current = sorted(k for k in self._tokens if key_intersects(k, watcher.key_expr))
            watcher.hold().acquire()
        try:
            for key in current:
                watcher.deliver(key, True)
        finally:
            watcher.hold().release()

    def remove_watcher(self, watcher: _Delivery) -> None:
        watcher.close()
        with self._lock:
            self._watchers.discard(watcher)

    def _notify(self, key: str, alive: bool) -> None:
        with self._lock:
            targets = [w for w in self._watchers if key_intersects(w.key_expr, key)]
        for watcher in targets:
            watcher.deliver(key, alive)


class _MemoryLatest:
    """The latest value served on ``key``; ``set`` stores it and publishes it."""

    def __init__(self, key: str, transport: InMemoryTransport) -> None:
        self.key = key
        self.value: bytes | None = None
        self._transport = transport
        self._handle: Handle | None = None

    def set(self, payload: bytes) -> None:
        """Store ``payload`` as the answer to queries, then publish it on ``key``."""
        self.value = bytes(payload)
        self._transport.publish(self.key, self.value)

    def close(self) -> None:
        """Stop answering queries."""
        if self._handle is not None:
            self._handle.close()


class InMemoryTransport(HandleRegistry):
    """A ``Transport`` for one simulated service, attached to a shared ``InMemoryBus``."""

    def __init__(self, bus: InMemoryBus | None = None) -> None:
        self.bus = bus if bus is not None else InMemoryBus()
        super().__init__()

    def publish(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        """Deliver ``payload`` to every matching subscriber now, on this thread (``reliable`` is moot)."""
        self._check_open()
        self.bus.publish(key, payload if isinstance(payload, bytes) else bytes(payload))

    def subscribe(self, key_expr: str, callback: Callback) -> Handle:
        """Call ``callback(key, payload)`` for every payload published on a key matching ``key_expr``."""
        self._check_open()
        delivery = _Delivery(key_expr, callback)
        self.bus.add_subscriber(delivery)
        return self._track(lambda: self.bus.remove_subscriber(delivery))

    def serve_latest(self, key: str) -> LatestValue:
        """Answer queries matching ``key`` with the last value set on the returned object."""
        self._check_open()
        validate_key_expr(key)
        latest = _MemoryLatest(key, self)
        self.bus.add_latest(latest)
        latest._handle = self._track(lambda: self.bus.remove_latest(latest))
        return latest

    def query(self, key_expr: str, timeout: float = 1.0) -> list[tuple[str, bytes]]:
        """(key, value) of every set ``serve_latest`` matching ``key_expr``; answers at once."""
        self._check_open()
        return self.bus.query(key_expr)

    def declare_token(self, key: str) -> Handle:
        """Announce liveliness on ``key`` until the handle or this transport is closed."""
        self._check_open()
        self.bus.declare_token(key)
        return self._track(lambda: self.bus.undeclare_token(key))

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle:
        """Report tokens matching ``key_expr``: those alive now first, then every change."""
        self._check_open()
        watcher = _Delivery(key_expr, callback)
        self.bus.add_watcher(watcher)
        return self._track(lambda: self.bus.remove_watcher(watcher))

    def alive(self, key_expr: str, timeout: float = 1.0) -> list[str]:
        """Sorted keys of the tokens matching ``key_expr`` alive now."""
        self._check_open()
        return self.bus.alive(key_expr)

    def close(self) -> None:
        """Undeclare everything this transport declared (its tokens die with it); idempotent."""
        with self._lock:
            self._closed = True
            handles = list(self._handles)
        for handle in handles:
            handle.close()

    def __enter__(self) -> InMemoryTransport:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

