"""dashboard service shell: the only dashboard file that touches the bus.

Subscribes to every run's graph reports, local-graph reports and stats beats (``watch_run`` narrows
that to one run), asks the graph and local-graph queryables for their latest report at start, and
serves the page over HTTP (``web.py``). Each new report of either kind is pushed to the page's event
streams of its run; the service list at most every ``services_push_s``.
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

from proto import topics
from proto.messages import GraphReport, LocalGraphReport, ServiceStats
from services.bus.base import Transport
from services.dashboard.config import DashboardConfig
from services.dashboard.core import DashboardState
from services.dashboard.coverage import run_coverage
from services.dashboard.web import DashboardServer, EventHub, WebMetrics, to_json
from services.runtime.config import parse_config, write_config
from services.runtime.shell import Inbox, ServiceShell, setup_logging

SERVICE = "dashboard"
STALLED_AFTER_S = 5.0
log = logging.getLogger(SERVICE)


def _web_metrics(shell: ServiceShell) -> WebMetrics:
    m = shell.metrics
    return WebMetrics(
        sse_clients=m.gauge("causeway_dashboard_sse_clients", "Open /events streams"),
        requests=m.counter("causeway_dashboard_http_requests", "HTTP requests, by route", ("path",)),
        pushed=m.counter("causeway_dashboard_updates_pushed", "Events written to /events streams, by event",
                         ("event",)))


def run_of(key: str) -> str:
    """The ``<run>`` segment of a ``causeway/<run>/...`` key."""
    return key.split("/", 2)[1]


class _Pusher:
    """Turns state changes into events for the streams that are listening, encoding each once."""

    def __init__(self, state: DashboardState, hub: EventHub, services_every_s: float) -> None:
        self.state, self.hub, self.services_every_s = state, hub, services_every_s
        self._stats_runs: set[str] = set()
        self._last_services = 0.0
        self._known_runs: list[str] = []

    @property
    def run_count(self) -> int:
        return len(self._known_runs)

    def reports(self, runs: set[str], now: float) -> None:
        for run in runs:
            if self.hub.watching(run):
                self.hub.push(run, "snapshot", to_json(self.state.snapshot(run, now)))
        run_ids = self.state.run_ids()
        if runs or run_ids != self._known_runs:
            self._known_runs = run_ids
            self.hub.push(None, "runs", to_json(self.state.runs(now)))

    def services(self, runs: set[str], now: float) -> None:
        self._stats_runs |= runs
        if not self._stats_runs or now - self._last_services < self.services_every_s:
            return
        for run in self._stats_runs:
            if self.hub.watching(run):
                services = self.state.services(run, now)
                self.hub.push(run, "services", to_json({"run": run, "server_time": now, "services": services,
                                                        "induced_coverage": run_coverage(services),
                                                        "live_history": self.state.live_history(run)}))
        self._stats_runs.clear()
        self._last_services = now


class _LoopWatch:
    """When the bus loop last went round: /healthz fails once it stalls."""

    def __init__(self) -> None:
        self.last = time.monotonic()

    def tick(self) -> None:
        self.last = time.monotonic()

    def healthy(self) -> bool:
        return time.monotonic() - self.last < STALLED_AFTER_S


def _take(inbox: Inbox, wait_s: float) -> list[tuple[str, Any]]:
    """Wait up to ``wait_s`` for one message, then everything else already queued."""
    first = inbox.get(wait_s)
    return ([first] if first is not None else []) + inbox.drain()


def _apply(state: DashboardState, reports: list[tuple[str, GraphReport | LocalGraphReport]],
           beats: list[tuple[str, ServiceStats]], now: float) -> tuple[set[str], set[str]]:
    """Feed the state; returns (runs with a new report of either kind, runs with a new beat)."""
    new_reports = set()
    for key, report in reports:
        add = state.add_local_report if isinstance(report, LocalGraphReport) else state.add_report
        if add(run_of(key), report, now):
            new_reports.add(run_of(key))
    for key, beat in beats:
        state.add_stats(run_of(key), beat, now)
    return new_reports, {run_of(key) for key, _ in beats}


def run(cfg: DashboardConfig, transport: Transport | None = None) -> None:
    shell = ServiceShell(SERVICE, cfg, transport)
    try:
        if threading.current_thread() is threading.main_thread():
            shell.install_signal_handlers()
        write_config(cfg, Path(cfg.run_dir) / "config" / f"{SERVICE}-{cfg.instance}.json")
        _serve(shell, cfg)
    finally:
        shell.close()


def _serve(shell: ServiceShell, cfg: DashboardConfig) -> None:
    """Wire bus -> state -> HTTP, then loop until stopped."""
    state = DashboardState(cfg.history_points, cfg.max_runs, cfg.max_services, cfg.stale_after_s, cfg.local_examples)
    web_metrics = _web_metrics(shell)
    runs_gauge = shell.metrics.gauge("causeway_dashboard_runs", "Runs the dashboard knows")
    hub = EventHub(cfg.max_sse_clients, web_metrics.sse_clients)
    graphs = shell.inbox("graphs", GraphReport, maxsize=256)
    local_graphs = shell.inbox("local_graphs", LocalGraphReport, maxsize=256)
    beats = shell.inbox("stats", ServiceStats, maxsize=4096)
    shell.subscribe(topics.graph(cfg.watch_run), graphs)
    shell.subscribe(topics.local(cfg.watch_run), local_graphs)
    shell.subscribe(topics.stats(cfg.watch_run), beats)
    watch = _LoopWatch()
    server = DashboardServer((cfg.http_host, cfg.http_port), state, hub, web_metrics, watch.healthy, cfg.heartbeat_s)
    server.start()
    log.info("serving the dashboard on http://%s:%d/", cfg.http_host, server.port)
    try:
        for topic, inbox in ((topics.graph(cfg.watch_run), graphs), (topics.local(cfg.watch_run), local_graphs)):
            for key, payload in shell.transport.query(topic, timeout=2.0):
                inbox.on_payload(key, payload)  # the same validation and counting as a published report
        pusher = _Pusher(state, hub, cfg.services_push_s)
        while not shell.stopping.is_set():
            shell.poll_control()
            now = time.time()
            reports = _take(graphs, 0.1) + local_graphs.drain()
            new_reports, beaten = _apply(state, reports, beats.drain(), now)
            pusher.reports(new_reports, now)
            pusher.services(beaten, now)
            runs_gauge.set(pusher.run_count)
            watch.tick()
            shell.beat({"runs": pusher.run_count, "sse_clients": len(hub)})
    finally:
        server.stop()


def main(argv: list[str] | None = None) -> None:
    setup_logging(SERVICE)
    run(parse_config(DashboardConfig, argv))


if __name__ == "__main__":
    main(sys.argv[1:])
