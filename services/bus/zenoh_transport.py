"""``Transport`` over a real Zenoh session: a client of the router (see ``router.py``).

Facts about eclipse-zenoh 1.10.2 that shaped this module (measured here):

- A plain Python callable given as a handler runs on a Python thread that Zenoh starts per
  subscriber/queryable ("pyo3-closure"; ``zenoh.handlers.Callback(..., indirect=True)``, the
  default), not on a network thread; the thread's queue is bounded, so a slow callback pushes back
  on BLOCK publishers instead of growing memory. Zenoh prints "callback error" and a traceback for
  an exception escaping a callback and carries on; we log it through ``logging`` instead.
- Those callback threads are *non-daemon*: a process that exits (even by an uncaught exception)
  with a callback subscriber still declared hangs forever in interpreter shutdown, so a crashed
  service would never be seen to die. Every open ``ZenohTransport`` is therefore closed by a hook
  that ``threading`` runs before it joins non-daemon threads. (A ``FifoChannel`` drained by a
  daemon thread is no way out: exiting while that thread waits in ``recv`` aborts the process with
  "FATAL: exception not rethrown".)
- BLOCK is not forever: a queue blocked longer than ``transport/link/tx/queue/congestion_control/
  block/wait_before_close`` (5 s by default) gives up and the messages are lost. A subscriber
  that stalled 7 s in its callback received 417 of 1000 messages of 100 KB, and the link then
  carried on. Callbacks must hand off to a bounded queue and return.
- ``session.get`` defaults to ``QueryTarget.BEST_MATCHING`` and to consolidating replies per
  key; ``query`` asks ``ALL`` queryables with no consolidation, so every server answers.
- A query that matches no queryable returns at once (the router knows), not after the timeout;
  ``liveliness().get`` likewise. Both return a handler that ends when the query is complete.
- A queryable sees queries from its own session too (``allowed_origin`` defaults to ANY).
- A liveliness subscriber with ``history=True`` reports the tokens alive now as PUT samples; a
  token's DELETE arrives within milliseconds of its holder's process being SIGKILLed, because the
  router sees the TCP link close.
- A liveliness subscriber sometimes gets a token's PUT twice (6 runs in 100 on a loaded machine,
  about 1 in 100 idle, when the holder's session is new), and a ``liveliness().get`` issued right after the
  first PUT can still miss the token for ~20 ms. ``watch_liveliness`` reports changes only, so
  duplicates never reach callers; ``alive`` is a snapshot and may lag a watcher slightly. Two
  sessions holding the same key show as one token; give every process its own key.
- Undeclaring after ``session.close()`` is a no-op, so ``close`` can undeclare in any order.
"""
from __future__ import annotations

import atexit
import logging
import threading
from typing import Any, Callable, Protocol

import zenoh

from services.bus.handles import HandleRegistry, OnceHandle
from services.bus.base import Callback, Handle, LatestValue, LivelinessCallback
from services.bus.credentials import Credentials
from services.bus.router import client_config

logger = logging.getLogger(__name__)

_open_transports: set[ZenohTransport] = set()
_open_lock = threading.Lock()


def _close_open_transports() -> None:
    """Close every transport still open, so Zenoh's non-daemon callback threads end (see above)."""
    with _open_lock:
        transports = list(_open_transports)
    for transport in transports:
        transport.close()


# Runs before threading joins non-daemon threads; atexit would run after, i.e. never.
getattr(threading, "_register_atexit", atexit.register)(_close_open_transports)


class _Undeclarable(Protocol):
    def undeclare(self) -> None: ...


def _guarded(what: str, function: Callable[[Any], None]) -> Callable[[Any], None]:
    """``function`` with every exception logged, so a user callback never breaks a Zenoh thread."""

    def guarded(argument: Any) -> None:
        try:
            function(argument)
        except Exception:
            logger.exception("callback for %s raised; message dropped", what)

    return guarded


class _TokenTransitions:
    """The tokens a watcher believes alive; lets through only real appear/disappear changes."""

    def __init__(self) -> None:
        self._alive: set[str] = set()
        self._lock = threading.Lock()

    def changed(self, key: str, alive: bool) -> bool:
        with self._lock:
            if (key in self._alive) == alive:
                return False
            if alive:
                self._alive.add(key)
            else:
                self._alive.discard(key)
            return True


class _ZenohLatest:
    """The value a ``serve_latest`` queryable answers with; ``set`` stores it, then publishes it."""

    def __init__(self, key: str, transport: ZenohTransport) -> None:
        self.key = key
        self._value: bytes | None = None
        self._transport = transport
        self._handle: Handle | None = None

    def set(self, payload: bytes) -> None:
        """Answer later queries with ``payload`` and publish it reliably on ``key``."""
        self._value = bytes(payload)
        self._transport.publish(self.key, self._value, reliable=True)

    def answer(self, query: zenoh.Query) -> None:
        """Reply to ``query`` with the latest value, or not at all when none was set yet."""
        value = self._value
        if value is not None:
            query.reply(self.key, value)

    def close(self) -> None:
        """Stop answering queries."""
        if self._handle is not None:
            self._handle.close()


class ZenohTransport(HandleRegistry):
    """A ``Transport`` on a Zenoh client session connected to the router at ``connect``.

    Opening fails with ``zenoh.ZError`` when no router answers; call ``wait_for_router`` first
    where the router may still be starting. Use it as a context manager, or ``close`` it; an
    interpreter exit closes whatever is still open. ``credentials``: the user this client
    authenticates as, where the router requires one (:mod:`services.bus.roles`); a router that
    denies one of its puts or declarations drops it silently. ``root_ca``: the CA certificate that
    signed a ``tls/`` router's certificate.
    """

    def __init__(self, connect: str, credentials: Credentials | None = None, root_ca: str = "") -> None:
        self.connect = connect
        self._session = zenoh.open(client_config(connect, credentials, root_ca))
        self._publishers: dict[tuple[str, bool], zenoh.Publisher] = {}
        super().__init__()
        with _open_lock:
            _open_transports.add(self)

    def publish(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        """Put ``payload`` on ``key``; ``reliable`` blocks under congestion (BLOCK), else DROP.

        One publisher is declared per (key, reliable) and kept until ``close``: keys are a small
        fixed set per service (see ``proto``), so the cache stays small.
        """
        self._publisher(key, reliable).put(payload)

    def subscribe(self, key_expr: str, callback: Callback) -> Handle:
        """Call ``callback(key, payload)`` on a Zenoh-owned thread for each PUT matching ``key_expr``."""

        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                callback(str(sample.key_expr), sample.payload.to_bytes())

        self._check_open()
        handler = _guarded(f"subscriber {key_expr!r}", on_sample)
        return self._track_entity(self._session.declare_subscriber(key_expr, handler))

    def serve_latest(self, key: str) -> LatestValue:
        """Declare a queryable on ``key`` answering with the value last set on the returned object."""
        self._check_open()
        latest = _ZenohLatest(key, self)
        handler = _guarded(f"queryable {key!r}", latest.answer)
        latest._handle = self._track_entity(self._session.declare_queryable(key, handler))
        return latest

    def query(self, key_expr: str, timeout: float = 1.0) -> list[tuple[str, bytes]]:
        """(key, payload) of every Ok reply from all queryables matching ``key_expr``."""
        self._check_open()
        replies = self._session.get(
            key_expr,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        return [(str(r.ok.key_expr), r.ok.payload.to_bytes()) for r in replies if r.ok is not None]

    def declare_token(self, key: str) -> Handle:
        """Declare a liveliness token on ``key``; it dies with the handle, the session or the process."""
        self._check_open()
        return self._track_entity(self._session.liveliness().declare_token(key))

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle:
        """Report tokens matching ``key_expr``: alive now first (history), then PUT->True, DELETE->False.

        Duplicate PUTs (see the module notes) are filtered: each call is a change.
        """
        transitions = _TokenTransitions()

        def on_sample(sample: zenoh.Sample) -> None:
            key, alive = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
            if transitions.changed(key, alive):
                callback(key, alive)

        self._check_open()
        handler = _guarded(f"liveliness watcher {key_expr!r}", on_sample)
        liveliness = self._session.liveliness()
        return self._track_entity(liveliness.declare_subscriber(key_expr, handler, history=True))

    def alive(self, key_expr: str, timeout: float = 1.0) -> list[str]:
        """Sorted keys of the liveliness tokens matching ``key_expr`` now."""
        self._check_open()
        replies = self._session.liveliness().get(key_expr, timeout=timeout)
        return sorted({str(r.ok.key_expr) for r in replies if r.ok is not None})

    def close(self) -> None:
        """Undeclare every publisher, subscriber, queryable and token, then close the session."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            handles, publishers = list(self._handles), list(self._publishers.values())
            self._publishers.clear()
        for handle in handles:
            handle.close()
        for publisher in publishers:
            publisher.undeclare()
        self._session.close()
        with _open_lock:
            _open_transports.discard(self)

    def __enter__(self) -> ZenohTransport:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _publisher(self, key: str, reliable: bool) -> zenoh.Publisher:
        with self._lock:
            if self._closed:
                raise RuntimeError("transport is closed")
            publisher = self._publishers.get((key, reliable))
            if publisher is None:
                congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
                publisher = self._session.declare_publisher(key, congestion_control=congestion)
                self._publishers[(key, reliable)] = publisher
            return publisher

    def _track_entity(self, entity: _Undeclarable) -> OnceHandle:
        return self._track(entity.undeclare)
