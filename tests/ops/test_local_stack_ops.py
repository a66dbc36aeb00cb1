"""The operator CLI against a real local stack: status, runtime scaling, a SIGKILL, checkpoint, stop.

One small stack (chain, 3 objects, one env-worker throttled to 500 steps/s) runs as a subprocess,
exactly as ``causeway run`` would; the commands run in this process through ``services.cli.main``.
"""
from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from services.bus.router import free_tcp_port
from services.cli import main as cli_main
from services.ops import status
from tests import waiting

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]


wait_for = waiting.wait_for

def start_stack(run_dir: Path, port: int) -> subprocess.Popen[str]:
    cmd = [sys.executable, "-m", "services.cli", "run", "--graph", "chain", "--num-objects", "3", "--workers", "1",
           "--router-port", str(port), "--metrics-base-port", "0", "--worker-max-steps-per-second", "500", "--progress", "false",
           "--run-dir", str(run_dir), "--max-seconds", "240", "--checkpoint-every-s", "600",
           "--evaluator-min-interval-s", "1", "--learner-publish-every-s", "1", "--dashboard-port", "0",
           "--evaluate", "false"]  # the operator commands are under test, not the post-run evaluation
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


class Operator:
    """Runs ``causeway <command> --run-dir <run>`` in this process and returns (exit code, stdout)."""

    def __init__(self, run_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
        self.run_dir, self.capsys = run_dir, capsys

    def __call__(self, *args: str) -> tuple[int, str]:
        self.capsys.readouterr()
        code = cli_main([*args, "--run-dir", str(self.run_dir)])
        return code, self.capsys.readouterr().out

    def status(self) -> dict[str, Any]:
        code, out = self("status", "--json")
        assert code == 0, out
        return json.loads(out)

    def processes(self) -> dict[str, Any]:
        return json.loads((self.run_dir / "processes.json").read_text())["processes"]


def rows(document: dict[str, Any], service: str) -> list[dict[str, Any]]:
    return [r for r in document["services"] if r["service"] == service]


def alive_with_rates(document: dict[str, Any], workers: int) -> bool:
    """``workers`` env-workers with a rate, and the learner and the evaluator alive and beating."""
    workers_ok = [r for r in rows(document, "env-worker") if r["state"] == "alive" and r["rate"]]
    learners = [r for s in ("dynamics-learner", "graph-evaluator") for r in rows(document, s)
                if r["state"] == "alive" and r["beats"]]
    return len(workers_ok) == workers == len(rows(document, "env-worker")) and len(learners) == 2


def test_status_scale_kill_checkpoint_stop(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run_dir = tmp_path / "run"
    stack = start_stack(run_dir, free_tcp_port())
    causeway = Operator(run_dir, capsys)
    try:
        wait_for(lambda: (run_dir / "processes.json").exists(), 30, "the process table")
        first = wait_for(lambda: (d := causeway.status()) and alive_with_rates(d, 1) and d, 60, "three services beating")
        assert {"env-worker", "dynamics-learner", "graph-evaluator"} <= {r["service"] for r in first["services"]}
        one_worker = first["totals"]["env-worker"]["rate"]
        learner_pid = causeway.processes()["dynamics-learner"]["pid"]

        # a new worker imports torch and the env before it is alive: 10 s (the default) is too short
        # on a loaded 2-core machine
        code, out = causeway("scale", "env-worker", "2", "--timeout-s", "90")
        assert code == 0 and "env-worker: 1 -> 2 alive" in out, out
        two = wait_for(lambda: (d := causeway.status()) and alive_with_rates(d, 2) and d, 30, "two env-workers beating")
        assert two["totals"]["env-worker"]["rate"] > 1.5 * one_worker, (one_worker, two["totals"])
        assert causeway.processes()["dynamics-learner"]["pid"] == learner_pid  # raised without a restart

        transitions = rows(two, "dynamics-learner")[0]["values"]["env_steps"]
        code, out = causeway("scale", "env-worker", "1", "--timeout-s", "90")
        assert code == 0 and "env-worker: 2 -> 1 alive" in out, out
        after = causeway.status()
        assert [r["state"] for r in rows(after, "env-worker")] == ["alive"]
        assert wait_for(lambda: rows(causeway.status(), "dynamics-learner")[0]["values"]["env_steps"] > transitions,
                        20, "the learner's transitions to keep rising")

        _kill_a_worker_while_watching(causeway, run_dir)

        checkpoint = run_dir / "checkpoints" / "dynamics-learner-0.pt"
        before = checkpoint.stat().st_mtime if checkpoint.exists() else 0.0
        code, out = causeway("checkpoint")
        assert code == 0 and "dynamics-learner/0" in out and "graph-evaluator/0" in out, out
        wait_for(lambda: checkpoint.exists() and checkpoint.stat().st_mtime > before, 15, "the commanded checkpoint")

        code, out = causeway("stop")
        assert code == 0 and "stopped:" in out, out
        stack_out, _ = stack.communicate(timeout=180)
    finally:
        if stack.poll() is None:
            stack.send_signal(signal.SIGINT)
            stack.communicate(timeout=60)
    assert stack.returncode == 0, stack_out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["stopped_because"] == "stopped by an operator"
    assert summary["restarts"] >= 1


def _kill_a_worker_while_watching(causeway: Operator, run_dir: Path) -> None:
    """SIGKILL the env-worker while a status listens: it is seen gone, then back after the restart.

    The listening status runs on a thread of this process (modules already imported), so it is
    surely watching before the kill even on a loaded machine."""
    name, entry = next((n, p) for n, p in causeway.processes().items() if n.startswith("env-worker-"))
    out = io.StringIO()
    watch = threading.Thread(target=status.main, args=(["--json", "--listen-s", "5", "--run-dir", str(run_dir)], out))
    watch.start()
    time.sleep(1.0)
    os.kill(entry["pid"], signal.SIGKILL)
    watch.join(timeout=30)
    (row,) = rows(json.loads(out.getvalue()), "env-worker")
    assert row["state"] in ("gone", "restarted"), row  # restarted: gone, and back within the window
    wait_for(lambda: causeway.processes()[name]["pid"] != entry["pid"], 20, "the supervisor's restart")
    back = wait_for(lambda: (d := causeway.status()) and [r["state"] for r in rows(d, "env-worker")] == ["alive"] and d,
                    20, "the restarted env-worker")
    assert back["totals"]["env-worker"]["alive"] == 1
