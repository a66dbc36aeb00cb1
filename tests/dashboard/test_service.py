"""The dashboard service over the in-memory bus, its HTTP API and event stream on loopback."""
from __future__ import annotations

import functools
import http.client
import json
import threading
import urllib.error
import urllib.request
from dataclasses import replace

import numpy as np
import pytest

from proto import topics
from proto.codec import encode
from proto.messages import Control
from services.bus.memory import InMemoryBus, InMemoryTransport
from services.bus.router import free_tcp_port
from services.dashboard import service
from services.dashboard.config import DashboardConfig
from tests.dashboard.reports import make_local_report, make_report, make_stats
from tests import waiting

RUN = "run-a"


wait_for = functools.partial(waiting.wait_for, interval=0.02)

def get(port: int, path: str) -> tuple[int, dict[str, str], bytes]:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as reply:
            return reply.status, dict(reply.headers), reply.read()
    except urllib.error.HTTPError as error:
        return error.code, dict(error.headers), error.read()


class EventStream:
    """A minimal text/event-stream reader."""

    def __init__(self, port: int, run: str) -> None:
        self.connection = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
        self.connection.request("GET", f"/events?run={run}")
        self.response = self.connection.getresponse()

    def next(self, comments: bool = False) -> tuple[str, str]:
        """(event, data) of the next event, or ("comment", text) when ``comments``."""
        event, data = "message", []
        while True:
            line = self.response.readline().decode().rstrip("\n")
            if line.startswith(":") and comments:
                return "comment", line[1:].strip()
            if line.startswith("event: "):
                event = line[len("event: "):]
            elif line.startswith("data: "):
                data.append(line[len("data: "):])
            elif line == "" and data:
                return event, "\n".join(data)

    def until(self, event: str) -> dict:
        while True:
            name, data = self.next()
            if name == event:
                return json.loads(data)

    def close(self) -> None:
        self.connection.close()


@pytest.fixture
def dashboard(tmp_path):
    bus = InMemoryBus()
    publisher = InMemoryTransport(bus)
    latest = publisher.serve_latest(topics.graph(RUN, "cdl"))
    latest.set(encode(make_report(3, version=1, errors=3)))  # answered to the dashboard's query at start
    latest_local = publisher.serve_latest(topics.local(RUN, "cdl"))
    latest_local.set(encode(make_local_report(3, version=1, errors=2)))  # likewise
    cfg = DashboardConfig(run_id="dash", run_dir=str(tmp_path), http_host="127.0.0.1", http_port=free_tcp_port(),
                          metrics_port=free_tcp_port(), max_sse_clients=2, heartbeat_s=0.3, services_push_s=0.1)
    thread = threading.Thread(target=service.run, args=(cfg, InMemoryTransport(bus)), daemon=True)
    thread.start()
    wait_for(lambda: _status(cfg.http_port, "/healthz") == 200, 10, "the dashboard to serve")
    yield cfg, publisher, latest, latest_local
    publisher.publish(topics.control("dash", "all"), encode(Control("stop")))
    thread.join(10)
    assert not thread.is_alive()
    assert (tmp_path / "config" / "dashboard-0.json").exists()


def _status(port: int, path: str) -> int | None:
    try:
        return get(port, path)[0]
    except OSError:
        return None


def test_api_serves_the_run_list_snapshots_and_the_page(dashboard) -> None:
    cfg, publisher, *_ = dashboard
    publisher.publish(topics.graph("run-b", "cdl"), encode(make_report(2, version=4)))
    listed = lambda: [r["run"] for r in json.loads(get(cfg.http_port, "/api/runs")[2])["runs"]]  # noqa: E731
    # graphs first, newest first; then the dashboard's own run, known from its own stats beats only
    wait_for(lambda: listed() == ["run-b", RUN, "dash"], 5, "both runs and the dashboard's own")
    status, headers, body = get(cfg.http_port, f"/api/runs/{RUN}")
    snapshot = json.loads(body)
    assert status == 200 and headers["Content-Type"] == "application/json"
    assert snapshot["graph"]["weights_version"] == 1 and len(snapshot["graph"]["cells"]) == 9
    assert get(cfg.http_port, "/api/runs/nope")[0] == 404
    status, headers, page = get(cfg.http_port, "/")
    assert status == 200 and b'id="heatmap-learned"' in page
    assert "default-src 'self'" in headers["Content-Security-Policy"]
    status, headers, _ = get(cfg.http_port, "/static/app.js")
    assert status == 200 and headers["Content-Type"].startswith("text/javascript")
    assert get(cfg.http_port, "/static/../service.py")[0] == 404
    assert get(cfg.http_port, "/static/%2e%2e/core.py")[0] == 404
    assert get(cfg.http_port, "/nothing")[0] == 404


def test_events_push_each_new_report_and_heartbeats(dashboard) -> None:
    cfg, publisher, latest, _ = dashboard
    stream = EventStream(cfg.http_port, RUN)
    try:
        assert stream.response.getheader("Content-Type") == "text/event-stream"
        assert stream.until("runs")[0]["run"] == RUN
        assert stream.until("snapshot")["graph"]["weights_version"] == 1
        latest.set(encode(make_report(3, version=2, errors=1)))
        pushed = stream.until("snapshot")
        assert pushed["graph"]["weights_version"] == 2 and [p["env_steps"] for p in pushed["history"]] == [5000, 10000]
        publisher.publish(topics.stats(RUN, "env-worker", "0"), encode(make_stats("env-worker", env_steps=7.0)))
        beats = stream.until("services")
        assert beats["run"] == RUN and beats["services"][0]["values"] == {"env_steps": 7.0}
        assert stream.next(comments=True) == ("comment", "heartbeat")
    finally:
        stream.close()


def test_event_streams_are_capped_and_metrics_are_exported(dashboard) -> None:
    cfg, *_ = dashboard
    streams = [EventStream(cfg.http_port, RUN) for _ in range(2)]
    try:
        for s in streams:
            s.until("snapshot")
        status, headers, _ = get(cfg.http_port, f"/events?run={RUN}")
        assert status == 503 and headers["Retry-After"] == "10"
        metrics = get(cfg.metrics_port, "/metrics")[2].decode()
        assert "causeway_dashboard_sse_clients 2.0" in metrics
        assert 'causeway_dashboard_http_requests_total{path="/events"} 3.0' in metrics
        assert 'causeway_dashboard_updates_pushed_total{event="snapshot"}' in metrics
        assert 'causeway_dashboard_http_requests_total{path="other"}' in metrics  # labels exist up front
    finally:
        for s in streams:
            s.close()


def test_bad_messages_are_counted_and_survived(dashboard) -> None:
    cfg, publisher, latest, _ = dashboard
    publisher.publish(topics.graph(RUN, "cdl"), b"\x93 not msgpack")
    publisher.publish(topics.stats(RUN, "x", "0"), encode(make_report(2)))  # a report where stats belong
    latest.set(encode(make_report(3, version=5)))
    wait_for(lambda: json.loads(get(cfg.http_port, f"/api/runs/{RUN}")[2])["graph"]["weights_version"] == 5, 5,
             "the next good report")
    metrics = get(cfg.metrics_port, "/metrics")[2].decode()
    assert 'causeway_messages_rejected_total{reason="malformed"} 1.0' in metrics
    assert 'causeway_messages_rejected_total{reason="unexpected_type"} 1.0' in metrics


def snapshot_of(port: int, run: str) -> dict:
    status, _, body = get(port, f"/api/runs/{run}")
    return json.loads(body) if status == 200 else {}


def test_local_reports_are_queried_at_start_and_served_beside_the_graph(dashboard) -> None:
    cfg, publisher, _, _ = dashboard
    both = snapshot_of(cfg.http_port, RUN)
    local = both["local_graph"]
    assert both["graph"]["weights_version"] == 1 and local["weights_version"] == 1
    assert local["estimator"] == "pcmi" and local["kind"] == "cdl" and local["num_examples"] == 4
    first = local["examples"][0]
    assert len(first["outcomes"]) == 9 and {o for row in first["outcomes"] for o in row} <= {"tp", "fp", "fn", "tn",
                                                                                               "self"}
    assert first["confusion"]["fp"] >= 1 and first["confusion"]["fn"] >= 1
    assert set(local["metrics"]) >= {"roc_auc", "pr_auc", "best_f1", "positive_rate"}

    elden = make_local_report(2, version=3, kind="elden", estimator="grad")
    publisher.publish(topics.local("local-only", "elden"), encode(elden))
    only = wait_for(lambda: snapshot_of(cfg.http_port, "local-only"), 5, "the local-only run")
    assert only["graph"] is None and only["history"] == [] and only["local_graph"]["estimator"] == "grad"
    runs = {r["run"]: r for r in json.loads(get(cfg.http_port, "/api/runs")[2])["runs"]}
    assert runs["local-only"]["has_local"] and not runs["local-only"]["has_graph"]
    assert runs["local-only"]["kind"] == "elden" and runs[RUN]["has_graph"] and runs[RUN]["has_local"]


def test_events_push_each_new_local_report(dashboard) -> None:
    cfg, _, _, latest_local = dashboard
    stream = EventStream(cfg.http_port, RUN)
    try:
        assert stream.until("snapshot")["local_graph"]["weights_version"] == 1
        latest_local.set(encode(make_local_report(3, version=2, errors=0)))
        pushed = stream.until("snapshot")
        local = pushed["local_graph"]
        assert local["weights_version"] == 2 and [p["env_steps"] for p in local["history"]] == [5000, 10000]
        assert all(e["confusion"]["fp"] == e["confusion"]["fn"] == 0 for e in local["examples"])
        assert pushed["graph"]["weights_version"] == 1 and len(pushed["history"]) == 1  # the graph curve is apart
    finally:
        stream.close()


def test_bad_local_reports_are_counted_and_survived(dashboard) -> None:
    cfg, publisher, _, latest_local = dashboard
    publisher.publish(topics.local(RUN, "cdl"), b"\x93 not msgpack")
    publisher.publish(topics.local(RUN, "cdl"), encode(make_report(2)))  # a graph report where local ones belong
    lopsided = replace(make_local_report(2), truth=np.zeros((4, 6, 6), np.uint8))  # truth not [K, d, d + 1]
    publisher.publish(topics.local(RUN, "cdl"), encode(lopsided))
    latest_local.set(encode(make_local_report(3, version=5)))
    wait_for(lambda: snapshot_of(cfg.http_port, RUN)["local_graph"]["weights_version"] == 5, 5, "the next good one")
    metrics = get(cfg.metrics_port, "/metrics")[2].decode()
    assert 'causeway_messages_rejected_total{reason="malformed"} 1.0' in metrics
    assert 'causeway_messages_rejected_total{reason="unexpected_type"} 1.0' in metrics
    assert 'causeway_messages_rejected_total{reason="inconsistent"} 1.0' in metrics
