"""A real Prometheus (Debian `prometheus`) scrapes a running local stack; PromQL returns live values.

The query answers what an operator's dashboard shows: the live graph F1 and the total env steps/s.
"""
from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from services.bus.router import free_tcp_port

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]


def promql(port: int, query: str) -> list[dict]:
    url = f"http://127.0.0.1:{port}/api/v1/query?" + urllib.parse.urlencode({"query": query})
    body = json.loads(urllib.request.urlopen(url, timeout=5).read())
    assert body["status"] == "success", body
    return body["data"]["result"]


def wait_for_value(port: int, query: str, timeout: float, at_least: float = 0.0) -> float:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            result = promql(port, query)
        except OSError:
            result = []
        if result and float(result[0]["value"][1]) > at_least:
            return float(result[0]["value"][1])
        time.sleep(1)
    raise AssertionError(f"no positive value for {query!r} within {timeout}s")


@pytest.mark.skipif(shutil.which("prometheus") is None, reason="Debian prometheus missing (make sysdeps installs it)")
def test_prometheus_scrapes_the_local_stack(tmp_path: Path) -> None:
    base = free_tcp_port() // 100 * 100 % 40000 + 20000
    stack = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "run", "--graph", "chain", "--num-objects", "3", "--max-seconds", "180",
         "--router-port", str(free_tcp_port()), "--metrics-base-port", str(base), "--dashboard-port", "0",
         "--run-dir", str(tmp_path / "run"), "--evaluator-min-interval-s", "1", "--learner-publish-every-s", "1",
         "--progress", "false", "--worker-max-steps-per-second", "1000", "--workers", "2"],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    prom_port = free_tcp_port()
    config = tmp_path / "prometheus.yml"
    config.write_text(
        "global: {scrape_interval: 1s, scrape_timeout: 1s}\nscrape_configs:\n"
        f"  - job_name: dynamics-learner\n    static_configs: [{{targets: ['127.0.0.1:{base + 1}']}}]\n"
        f"  - job_name: graph-evaluator\n    static_configs: [{{targets: ['127.0.0.1:{base + 2}']}}]\n"
        f"  - job_name: env-worker\n    static_configs: [{{targets: ['127.0.0.1:{base + 10}', '127.0.0.1:{base + 11}']}}]\n")
    prometheus = subprocess.Popen(
        ["prometheus", f"--config.file={config}", f"--storage.tsdb.path={tmp_path / 'tsdb'}",
         f"--web.listen-address=127.0.0.1:{prom_port}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        f1 = wait_for_value(prom_port, "causeway_graph_f1_ratio", 150)
        assert 0 < f1 <= 1
        # two workers throttled to 1,000 steps/s each: the total rate settles near 2,000
        steps_per_s = wait_for_value(prom_port, "sum(rate(causeway_env_steps_total[10s]))", 60, at_least=1200)
        assert steps_per_s < 2500
        up = promql(prom_port, "up")
        assert len(up) == 4 and all(r["value"][1] == "1" for r in up)
    finally:
        prometheus.terminate()
        stack.send_signal(signal.SIGINT)
        stack.wait(timeout=90)
        prometheus.wait(timeout=30)
