"""dashboard HTTP: the page, its JSON API and server-sent events, on stdlib ``http.server``. No bus.

``service.py`` owns the bus and hands this module two things: a ``SnapshotSource`` to read and an
``EventHub`` to push into. Routes:

    GET /                   the page (static/index.html)
    GET /static/<file>      its script, style sheet and icon (preloaded; nothing else on disk is served)
    GET /api/runs           {"server_time", "runs": [...]}
    GET /api/runs/<run>     the run's snapshot (core.DashboardState.snapshot: "graph", "history",
                            "local_graph", "services", "induced_coverage", "live_history"), 404 for an
                            unknown run
    GET /events?run=<run>   text/event-stream: "runs" and "snapshot" at once, then on every new report
                            (graph or local graph), "services" at most every few seconds, a comment
                            every heartbeat_s; 503 when full
    GET /healthz            200 {"status": "ok"} while the bus loop runs, 503 otherwise
"""
from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Callable, Protocol
from urllib.parse import parse_qs, unquote, urlsplit

from prometheus_client import Counter, Gauge

log = logging.getLogger("dashboard.http")

STATIC_DIR = Path(__file__).resolve().parent / "static"
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml", ".png": "image/png"}
PATH_LABELS = ("/", "/static", "/api/runs", "/api/runs/<run>", "/events", "/healthz", "other")
EVENTS = ("runs", "snapshot", "services")
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


class SnapshotSource(Protocol):
    """What the HTTP side reads (``core.DashboardState``)."""

    def runs(self, now: float) -> list[dict]: ...

    def snapshot(self, run: str, now: float) -> dict | None: ...


@dataclass(frozen=True)
class WebMetrics:
    sse_clients: Gauge
    requests: Counter
    """labels: path (one of PATH_LABELS)"""
    pushed: Counter
    """labels: event (one of EVENTS)"""


def to_json(document: object) -> bytes:
    return json.dumps(document, separators=(",", ":"), allow_nan=False).encode()


class Subscription:
    """One event-stream client: the newest payload of each event kind waits until the client takes it."""

    def __init__(self, run: str | None) -> None:
        self.run = run
        self._pending: dict[str, bytes] = {}
        self._closed = False
        self._ready = threading.Condition()

    def put(self, event: str, data: bytes) -> None:
        """Queue ``data``; an older payload of the same kind not yet sent is replaced (a slow client skips)."""
        with self._ready:
            self._pending.pop(event, None)
            self._pending[event] = data
            self._ready.notify()

    def take(self, timeout: float) -> list[tuple[str, bytes]] | None:
        """Pending events, [] after ``timeout`` with none, None once closed."""
        with self._ready:
            self._ready.wait_for(lambda: self._pending or self._closed, timeout)
            if self._closed:
                return None
            events, self._pending = list(self._pending.items()), {}
            return events

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._ready.notify()


class EventHub:
    """Fans events out to at most ``max_clients`` streams; ``run=None`` events go to every stream."""

    def __init__(self, max_clients: int, gauge: Gauge) -> None:
        self.max_clients, self._gauge = max_clients, gauge
        self._clients: set[Subscription] = set()
        self._closed = False
        self._lock = threading.Lock()

    def open(self, run: str | None) -> Subscription | None:
        """A new stream for ``run`` (None: run-list events only), or None when full or closed."""
        with self._lock:
            if self._closed or len(self._clients) >= self.max_clients:
                return None
            subscription = Subscription(run)
            self._clients.add(subscription)
            self._gauge.set(len(self._clients))
            return subscription

    def watching(self, run: str) -> bool:
        """Whether any stream follows ``run`` (so a snapshot is worth encoding)."""
        with self._lock:
            return any(c.run == run for c in self._clients)

    def __len__(self) -> int:
        with self._lock:
            return len(self._clients)

    def leave(self, subscription: Subscription) -> None:
        with self._lock:
            self._clients.discard(subscription)
            self._gauge.set(len(self._clients))

    def push(self, run: str | None, event: str, data: bytes) -> int:
        """Queue ``data`` for the streams of ``run`` (every stream when None); returns how many."""
        with self._lock:
            targets = [c for c in self._clients if run is None or c.run == run]
        for client in targets:
            client.put(event, data)
        return len(targets)

    def close(self) -> None:
        """End every stream (their handler threads return) and refuse new ones."""
        with self._lock:
            self._closed = True
            clients = list(self._clients)
        for client in clients:
            client.close()


class DashboardServer(ThreadingHTTPServer):
    """The HTTP server: one thread per connection, the shared state it serves hanging off it."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], source: SnapshotSource, hub: EventHub, metrics: WebMetrics,
                 healthy: Callable[[], bool], heartbeat_s: float) -> None:
        self.source, self.hub, self.metrics, self.healthy = source, hub, metrics, healthy
        self.heartbeat_s = heartbeat_s
        self.static = {p.name: (p.read_bytes(), CONTENT_TYPES[p.suffix])
                       for p in STATIC_DIR.iterdir() if p.suffix in CONTENT_TYPES}
        for label in PATH_LABELS:
            metrics.requests.labels(path=label)
        for event in EVENTS:
            metrics.pushed.labels(event=event)
        super().__init__(address, _Handler)

    @property
    def port(self) -> int:
        return int(self.server_address[1])

    def start(self) -> threading.Thread:
        thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.2},
                                  name="dashboard-http", daemon=True)
        thread.start()
        return thread

    def stop(self) -> None:
        self.hub.close()
        self.shutdown()
        self.server_close()


class _Handler(BaseHTTPRequestHandler):
    server: DashboardServer
    server_version = "causeway-dashboard"

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        url = urlsplit(self.path)
        path = url.path
        label, route = self._route(path)
        self.server.metrics.requests.labels(path=label).inc()
        route(path, parse_qs(url.query))

    def _route(self, path: str) -> tuple[str, Callable[[str, dict], None]]:
        if path in ("/", "/index.html"):
            return "/", lambda *_: self._static("index.html")
        if path.startswith("/static/"):
            return "/static", lambda p, _: self._static(p[len("/static/"):])
        if path == "/api/runs":
            return "/api/runs", lambda *_: self._json(200, {"server_time": time.time(),
                                                            "runs": self.server.source.runs(time.time())})
        if path.startswith("/api/runs/"):
            return "/api/runs/<run>", lambda p, _: self._snapshot(unquote(p[len("/api/runs/"):]))
        if path == "/events":
            return "/events", lambda _, query: self._events(query.get("run", [None])[0] or None)
        if path == "/healthz":
            return "/healthz", lambda *_: self._health()
        return "other", lambda *_: self._json(404, {"error": "not found"})

    def _static(self, name: str) -> None:
        found = self.server.static.get(name)
        if found is None:
            self._json(404, {"error": "not found"})
            return
        body, content_type = found
        self._send(200, body, content_type, {"Cache-Control": "no-cache"})

    def _snapshot(self, run: str) -> None:
        snapshot = self.server.source.snapshot(run, time.time())
        if snapshot is None:
            self._json(404, {"error": "unknown run", "run": run})
        else:
            self._json(200, snapshot)

    def _health(self) -> None:
        ok = self.server.healthy()
        self._json(200 if ok else 503, {"status": "ok" if ok else "bus loop stalled"})

    def _events(self, run: str | None) -> None:
        subscription = self.server.hub.open(run)
        if subscription is None:
            self._json(503, {"error": "too many event streams"}, {"Retry-After": "10"})
            return
        try:
            self.send_response(200)
            for name, value in {"Content-Type": "text/event-stream", "Cache-Control": "no-cache",
                                "X-Accel-Buffering": "no", **SECURITY_HEADERS}.items():
                self.send_header(name, value)
            self.end_headers()
            self.wfile.write(b"retry: 2000\n\n")
            self._stream(subscription, self._initial_events(run))
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            pass  # the browser went away
        finally:
            self.server.hub.leave(subscription)

    def _initial_events(self, run: str | None) -> list[tuple[str, bytes]]:
        now = time.time()
        events = [("runs", to_json(self.server.source.runs(now)))]
        snapshot = self.server.source.snapshot(run, now) if run else None
        if snapshot is not None:
            events.append(("snapshot", to_json(snapshot)))
        return events

    def _stream(self, subscription: Subscription, events: list[tuple[str, bytes]] | None) -> None:
        while events is not None:
            if not events:
                self.wfile.write(b": heartbeat\n\n")
            for event, data in events:
                self.wfile.write(b"event: " + event.encode() + b"\ndata: " + data + b"\n\n")
                self.server.metrics.pushed.labels(event=event).inc()
            self.wfile.flush()
            events = subscription.take(self.server.heartbeat_s)

    def _json(self, status: int, document: object, headers: dict[str, str] | None = None) -> None:
        self._send(status, to_json(document), "application/json", {"Cache-Control": "no-store", **(headers or {})})

    def _send(self, status: int, body: bytes, content_type: str, headers: dict[str, str]) -> None:
        self.send_response(status)
        for name, value in {"Content-Type": content_type, "Content-Length": str(len(body)),
                            **SECURITY_HEADERS, **headers}.items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 (http.server's signature)
        log.debug("%s " + format, self.address_string(), *args)
