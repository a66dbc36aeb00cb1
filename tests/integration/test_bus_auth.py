"""``causeway run --bus-auth`` end to end on loopback: every process connects with its own credentials
and the run reaches graph reports; an anonymous client is refused; a stop forged with an env-worker's
credentials does not stop the run, nor do worker 0's credentials send worker 1's beats (forged ones never
reach a reader, and the summary counts none); the operator commands, with the credentials of the run
directory, see the run and stop it.
"""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import zenoh

from proto import topics
from proto.codec import decode, encode
from proto.messages import Control, GraphReport, ServiceStats
from services.bus.credentials import read_credentials, role_file
from services.bus.router import free_tcp_port
from services.bus.zenoh_transport import ZenohTransport
from tests import waiting

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]


wait_for = waiting.wait_for

def causeway(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=180)


def dashboard_graph(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/runs/run", timeout=10) as response:
            return bool(json.loads(response.read()).get("graph"))
    except (urllib.error.URLError, OSError, ValueError):
        return False


def test_a_run_with_roles_learns_refuses_strangers_and_forgeries(tmp_path: Path) -> None:
    port, run_dir, page = free_tcp_port(), tmp_path / "run", free_tcp_port()
    connect = f"tcp/127.0.0.1:{port}"
    stack = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "run", "--bus-auth", "true", "--graph", "collider", "--num-objects", "3",
         "--max-seconds", "600", "--workers", "2", "--max-workers", "4", "--router-port", str(port), "--metrics-base-port", "0", "--run-dir", str(run_dir),
         "--evaluator-min-interval-s", "1", "--learner-publish-every-s", "1", "--progress", "false",
         "--worker-max-steps-per-second", "1000", "--dashboard-port", str(page), "--evaluate", "false"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(lambda: (run_dir / "processes.json").exists(), 120, "the process table")
        assert (run_dir / "secrets").stat().st_mode & 0o777 == 0o700
        with pytest.raises(zenoh.ZError):
            ZenohTransport(connect).close()
        reports: list[GraphReport] = []
        with ZenohTransport(connect, read_credentials(role_file(run_dir, "dashboard"))) as watcher:
            watcher.subscribe(topics.graph("run"), lambda k, p: reports.append(decode(p, GraphReport)))
            wait_for(lambda: reports, 300, "a graph report")
            beats: list[tuple[str, ServiceStats]] = []
            with ZenohTransport(connect, read_credentials(role_file(run_dir, "operator"))) as operator, \
                    ZenohTransport(connect, read_credentials(role_file(run_dir, "env-worker-0"))) as worker:
                operator.subscribe(topics.stats("run", "env-worker"), lambda k, p: beats.append((k, decode(p, ServiceStats))))
                worker.publish(topics.control("run", "all"), encode(Control("stop", issued_at=time.time())))
                forged = encode(ServiceStats(service="env-worker", instance="1", values={"env_steps": 1e12}, timestamp=time.time()))
                for _ in range(20):  # worker 1's key (refused by the router), then worker 0's own (ignored by the supervisor)
                    worker.publish(topics.stats("run", "env-worker", "1"), forged)
                    worker.publish(topics.stats("run", "env-worker", "0"), forged)
                    time.sleep(0.1)
                seen = len(reports)
                wait_for(lambda: len(reports) > seen + 1, 300, "graph reports after the forged stop and beats")
                ones = [s for k, s in beats if k == topics.stats("run", "env-worker", "1")]
                assert ones and all(s.values["env_steps"] < 1e12 for s in ones)  # worker 1's own beats only
                assert any(s.values["env_steps"] == 1e12 for k, s in beats if k.endswith("/0"))  # the other reached us
        assert stack.poll() is None
        wait_for(lambda: dashboard_graph(page), 120, "the dashboard's graph")  # its role reads graphs
        status = causeway("status", "--run-dir", str(run_dir), "--json")
        assert status.returncode == 0, status.stderr
        rows = json.loads(status.stdout)["services"]
        assert {"env-worker", "dynamics-learner", "graph-evaluator", "supervisor"} <= {r["service"] for r in rows}
        assert all(r["beats"] for r in rows if r["service"] == "env-worker")  # stats reach a late subscriber
        stop = causeway("stop", "--run-dir", str(run_dir), "--timeout-s", "120")
        assert stop.returncode == 0, stop.stdout + stop.stderr
        out, _ = stack.communicate(timeout=180)
    finally:
        if stack.poll() is None:
            stack.send_signal(signal.SIGINT)
            stack.communicate(timeout=180)
    assert stack.returncode == 0, out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stopped_because"] == "stopped by an operator"
    assert summary["restarts"] == 0 and 0.0 <= summary["f1"] <= 1.0
    assert 0 < summary["env_steps"] < 1e12  # no forged beat counted
