"""The bus behind a small interface: services publish and subscribe bytes on key expressions.

Two implementations share this contract: ``memory.InMemoryTransport`` (one process, for tests and
benchmarks) and ``zenoh_transport.ZenohTransport`` (real Zenoh, for every deployed service). Only a
service's ``service.py`` holds a Transport; cores never see one.
"""
from __future__ import annotations

from typing import Callable, Protocol

Callback = Callable[[str, bytes], None]
"""Called with (key, payload) on a transport thread: hand off to a bounded queue, never block long."""
LivelinessCallback = Callable[[str, bool], None]
"""Called with (token key, alive)."""


class Handle(Protocol):
    """Something declared on the bus (subscriber, queryable, token) that can be undeclared."""

    def close(self) -> None: ...


class Transport(Protocol):
    """Publish/subscribe of byte payloads, latest-value queries and liveliness tokens."""

    def publish(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        """Send ``payload`` on ``key``. ``reliable`` blocks under congestion instead of dropping."""

    def subscribe(self, key_expr: str, callback: Callback) -> Handle:
        """Deliver every payload published on keys matching ``key_expr``."""

    def serve_latest(self, key: str) -> "LatestValue":
        """Declare a queryable on ``key`` that answers with the last value set on the returned object."""

    def query(self, key_expr: str, timeout: float = 1.0) -> list[tuple[str, bytes]]:
        """Ask every queryable matching ``key_expr``; returns (key, payload) replies."""

    def declare_token(self, key: str) -> Handle:
        """Announce liveliness on ``key`` until closed (or until this process dies)."""

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle:
        """Report tokens matching ``key_expr`` appearing (True) and disappearing (False); current ones first."""

    def alive(self, key_expr: str, timeout: float = 1.0) -> list[str]:
        """Keys of the liveliness tokens matching ``key_expr`` right now."""

    def close(self) -> None: ...


class LatestValue(Protocol):
    """The value a ``serve_latest`` queryable answers with; ``set`` also publishes it."""

    def set(self, payload: bytes) -> None: ...

    def close(self) -> None: ...
