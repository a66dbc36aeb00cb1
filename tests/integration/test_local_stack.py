"""The real supervisor, router and services as processes on loopback: a short CDL run end to end.

Checks that graph reports arrive over Zenoh with sane scores, that every service serves /metrics,
that SIGKILL of the dynamics-learner is survived (restart, resume from its checkpoint), and that the
run directory holds what the README promises.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from proto import topics
from proto.codec import decode
from proto.messages import GraphReport, ServiceStats
from services.bus.credentials import Credentials, read_credentials, role_file
from services.bus.router import free_tcp_port
from services.bus.zenoh_transport import ZenohTransport
from tests import waiting

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]


wait_for = waiting.wait_for

class Watcher:
    """Subscribes to a run's graph reports and learner stats over the real router."""

    def __init__(self, connect: str, run_id: str, credentials: Credentials | None = None) -> None:
        self.bus = ZenohTransport(connect, credentials)
        self.reports: list[GraphReport] = []
        self.learner: list[ServiceStats] = []
        self.bus.subscribe(topics.graph(run_id), lambda k, p: self.reports.append(decode(p, GraphReport)))
        self.bus.subscribe(topics.stats(run_id, "dynamics-learner"), lambda k, p: self.learner.append(decode(p, ServiceStats)))


def watcher_credentials(run_dir: Path) -> Credentials | None:
    """The supervisor's credentials where the run has roles on the bus (its role reads graphs and stats)."""
    uses_auth = json.loads((run_dir / "config.json").read_text()).get("bus_auth")
    return read_credentials(role_file(run_dir, "supervisor")) if uses_auth else None


def start_stack(tmp_path: Path, port: int, metrics: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "services.cli", "run", "--graph", "collider", "--num-objects", "3",
           "--max-seconds", "240", "--router-port", str(port), "--metrics-base-port", str(metrics),
           "--run-dir", str(tmp_path / "run"), "--checkpoint-every-s", "2", "--evaluator-min-interval-s", "1",
           "--learner-publish-every-s", "1", "--progress", "false", "--worker-max-steps-per-second", "1000",
           "--dashboard-port", str(free_tcp_port())]
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_local_stack_learns_survives_sigkill_and_reports(tmp_path: Path) -> None:
    port, metrics = free_tcp_port(), 20000 + (os.getpid() % 2000) * 20
    stack = start_stack(tmp_path, port, metrics)
    run_dir = tmp_path / "run"
    try:
        table = wait_for(lambda: (run_dir / "processes.json").exists() and json.loads((run_dir / "processes.json").read_text()),
                         60, "the process table")
        watcher = Watcher(f"tcp/127.0.0.1:{port}", "run", watcher_credentials(run_dir))
        # ~15 s idle; the fresh-clone suite beside a compose build and a training run (load 5-9) took
        # over 120 s to the first report, so the wait is generous (it returns at the first report)
        report = wait_for(lambda: watcher.reports and watcher.reports[-1], 360, "a graph report")
        n = len(report.factor_names)
        assert n == 9 and report.cmi.shape == (9, 10) and np.isfinite(report.cmi).all()
        assert all(0.0 <= report.metrics[k] <= 1.0 for k in ("accuracy", "precision", "recall", "f1", "roc_auc"))
        assert report.metrics["accuracy"] > 0.5
        for offset in (1, 2, 10):
            body = urllib.request.urlopen(f"http://127.0.0.1:{metrics + offset}/metrics", timeout=5).read().decode()
            assert "causeway_messages_rejected_total" in body

        checkpoint = run_dir / "checkpoints" / "dynamics-learner-0.pt"
        wait_for(lambda: checkpoint.exists() and watcher.learner and watcher.learner[-1].values["updates"] > 20,
                 60, "a learner checkpoint")
        time.sleep(2.5)  # one more checkpoint interval, so the file holds > 20 updates
        killed_pid = table["processes"]["dynamics-learner"]["pid"]
        os.kill(killed_pid, signal.SIGKILL)
        new = wait_for(lambda: (t := json.loads((run_dir / "processes.json").read_text()))["processes"]["dynamics-learner"]["pid"] != killed_pid and t,
                       30, "the learner's restart")
        assert new["processes"]["dynamics-learner"]["restarts"] == 1
        resumed = wait_for(lambda: [s for s in watcher.learner if s.values.get("resumed_at_update", 0) > 0], 60,
                           "stats from the resumed learner")
        assert resumed[0].values["resumed_at_update"] > 20
        assert resumed[0].values["updates"] >= resumed[0].values["resumed_at_update"]
        version_before = watcher.reports[-1].weights_version
        wait_for(lambda: watcher.reports[-1].weights_version > version_before, 60, "a report from the restarted learner")
        watcher.bus.close()
    finally:
        stack.send_signal(signal.SIGINT)
        out, _ = stack.communicate(timeout=300)  # the post-run evaluation: minutes on a loaded machine
    assert stack.returncode == 0, out
    summary = json.loads((run_dir / "summary.json").read_text())
    for key in ("env", "env_options", "graph", "seed", "env_steps", "updates", "wall_seconds", "accuracy", "precision", "recall",
                "f1", "roc_auc", "best_threshold_f1", "factor_names", "learned_graph", "true_graph", "abstraction"):
        assert key in summary, key
    assert summary["restarts"] >= 1 and summary["env_steps"] > 0
    assert len(summary["learned_graph"]) == 9 and len(summary["learned_graph"][0]) == 10
    assert summary["factor_names"][:3] == ["obj0.color", "obj0.x", "obj0.y"]
    assert (run_dir / "graph.png").stat().st_size > 10_000
    assert (run_dir / "config.json").exists()
    # The final graph (Algorithm 1, line 8): the last learner checkpoint on all held-out transitions.
    final = summary["final_graph"]
    assert final["num_heldout"] >= summary["num_heldout"] and final["graph_updates"] >= summary["graph_updates"]
    assert np.array(final["cmi"]).shape == (9, 10) and 0.0 <= final["f1"] <= 1.0
    # The post-run evaluation: k-step colour accuracy of the final CDL model, ID and OOD.
    evaluation = summary["evaluation"]
    assert "error" not in evaluation, evaluation
    accuracy = evaluation["prediction"]["colour_accuracy"]
    assert set(accuracy) == {"id", "ood_0.1", "ood_1", "ood_10"}, accuracy
    assert all(len(curve) == 5 and all(0.0 <= x <= 1.0 for x in curve) for curve in accuracy.values())
    assert (run_dir / "evaluation.png").stat().st_size > 10_000
