"""Driving a real ``causeway run`` from outside for the chaos suite and its benchmark (issue 20 item 4):
the command, the process table, what a client of the run's router sees (stats beats, graph reports,
transition batches), a SIGKILL of one service and the wait for its recovery, and stopping the stack.
Used by ``tests/integration/test_chaos.py`` and ``benchmarks/bench_chaos.py``.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from proto import topics
from proto.codec import ProtocolError, decode
from proto.messages import GraphReport, ServiceStats, TransitionBatch
from services.bus.credentials import read_credentials, role_file
from services.bus.zenoh_transport import ZenohTransport
from tests.waiting import wait_for

REPO = Path(__file__).resolve().parents[1]
KINDS = ("env-worker-0", "dynamics-learner", "graph-evaluator", "intrinsic-reward", "policy-learner", "dashboard")
"""Process names in processes.json, killed in this order."""
OWN_PROGRESS = {"env-worker": "env_steps", "dynamics-learner": "updates", "graph-evaluator": "reports",
                "intrinsic-reward": "scored_batches", "policy-learner": "env_steps"}
"""The counter in each service's stats beat that shows it working again (the dashboard: its page)."""
BATCH_STEPS = 256


@dataclass
class Seen:
    """What the test sees on the bus: stats beats, graph reports, transition batches (with wall times)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    beats: list[ServiceStats] = field(default_factory=list)
    reports: list[tuple[float, GraphReport]] = field(default_factory=list)
    batches: list[tuple[float, int, int]] = field(default_factory=list)
    """(arrival time, steps, generation of the worker's life that sent it)."""

    def on_beat(self, key: str, payload: bytes) -> None:
        with contextlib.suppress(ProtocolError), self.lock:  # the fuzz test's payloads reach us too
            self.beats.append(decode(payload, ServiceStats))

    def on_report(self, key: str, payload: bytes) -> None:
        with contextlib.suppress(ProtocolError), self.lock:
            self.reports.append((time.time(), decode(payload, GraphReport)))

    def on_batch(self, key: str, payload: bytes) -> None:
        batch = decode(payload, TransitionBatch)
        with self.lock:
            self.batches.append((time.time(), len(batch), batch.life))

    def of(self, service: str, after: float = 0.0) -> list[ServiceStats]:
        with self.lock:
            return [b for b in self.beats if b.service == service and b.timestamp > after]

    def latest(self, service: str, key: str) -> float:
        beats = [b for b in self.of(service) if key in b.values]
        return beats[-1].values[key] if beats else 0.0

    def rising(self, service: str, key: str, after: float) -> bool:
        """Two beats of ``service`` sent after ``after`` show ``key`` growing."""
        values = [b.values[key] for b in self.of(service, after) if key in b.values]
        return len(values) >= 2 and values[-1] > values[0]

    def published(self, before: float) -> int:
        with self.lock:
            return sum(n for t, n, _ in self.batches if t <= before)

    def reports_after(self, t: float) -> list[GraphReport]:
        with self.lock:
            return [r for at, r in self.reports if at > t]


class Bus:
    """The test's two clients of the run's router: the supervisor's role (stats, graphs) and the
    dynamics-learner's (transitions), with the run directory's credentials."""

    def __init__(self, connect: str, run_dir: Path, run_id: str) -> None:
        self.seen = Seen()
        self.reader = ZenohTransport(connect, read_credentials(role_file(run_dir, "supervisor")))
        self.data = ZenohTransport(connect, read_credentials(role_file(run_dir, "dynamics-learner")))
        self.reader.subscribe(topics.stats(run_id), self.seen.on_beat)
        self.reader.subscribe(topics.graph(run_id), self.seen.on_report)
        self.data.subscribe(topics.transitions(run_id), self.seen.on_batch)

    def close(self) -> None:
        self.reader.close()
        self.data.close()


def command(run_dir: Path, port: int, metrics: int, dashboard: int, policy: bool = True,
            extra: tuple[str, ...] = (), max_seconds: float = 900) -> list[str]:
    """The chaos run: CDL on Chemical (collider, 3 objects), one worker at 500 steps/s, checkpoints
    every 2 s; with ``policy`` PPO with PredDiff, so all six kinds of service run. ``extra`` flags last."""
    cmd = [sys.executable, "-m", "services.cli", "run", "--graph", "collider", "--num-objects", "3",
           "--max-seconds", str(max_seconds), "--router-port", str(port), "--metrics-base-port", str(metrics),
           "--run-dir", str(run_dir), "--checkpoint-every-s", "2", "--evaluator-min-interval-s", "1",
           "--learner-publish-every-s", "1", "--progress", "false", "--worker-max-steps-per-second", "500",
           "--worker-batch-steps", str(BATCH_STEPS), "--dashboard-port", str(dashboard), "--evaluate", "false",
           "--seed", "3"]
    return cmd + (["--collector", "ppo", "--intrinsic", "preddiff"] if policy else []) + list(extra)


def start(cmd: list[str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def table(run_dir: Path) -> dict[str, Any]:
    try:
        return json.loads((run_dir / "processes.json").read_text())
    except (OSError, ValueError):
        return {}


def pid_alive(pid: int) -> bool:
    """Running (a zombie, already dead but not yet reaped by its parent, counts as gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1][0] != "Z"
    except (OSError, IndexError):
        return False


def stop(stack: subprocess.Popen, run_dir: Path, timeout: float = 300.0) -> str:
    """SIGINT the supervisor and collect its output; should that fail, kill it and whatever it left."""
    pids = [e["pid"] for e in table(run_dir).get("processes", {}).values() if e.get("pid")]
    if stack.poll() is None:
        stack.send_signal(signal.SIGINT)
    try:
        out, _ = stack.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        stack.kill()
        out, _ = stack.communicate()
    for pid in pids:
        if pid_alive(pid):
            os.kill(pid, signal.SIGKILL)
    return out


def kill_and_recover(bus: Bus, run_dir: Path, name: str, dashboard: int,
                     figures: dict[str, Any] | None = None) -> dict[str, Any]:
    """SIGKILL ``name``; wait for its restart and for the run to move on. Returns the figures, filled
    into ``figures`` as they come (a caller whose run ends meanwhile keeps what was measured)."""
    seen, service = bus.seen, name.rsplit("-", 1)[0] if name.startswith("env-worker") else name
    figures = {} if figures is None else figures
    before = table(run_dir)["processes"][name]
    steps, updates = seen.latest("env-worker", "env_steps"), seen.latest("dynamics-learner", "updates")
    version = seen.latest("dynamics-learner", "weights_version")
    lost = seen.latest("dynamics-learner", "lost_steps")
    killed_at = time.time()
    os.kill(before["pid"], signal.SIGKILL)
    figures.update(service=name, killed_at=killed_at)
    wait_for(lambda: table(run_dir)["processes"][name]["pid"] != before["pid"], 60, f"{name}'s restart")
    first = wait_for(lambda: seen.of(service, after=killed_at + 0.5), 120, f"a beat from the restarted {name}")[0]
    figures.update(restarts=table(run_dir)["processes"][name]["restarts"],
                   back_on_bus_s=round(first.timestamp - killed_at, 1))
    if service == "dynamics-learner":
        figures.update(learner_resumed(seen, first, killed_at, updates, version))
    if service == "env-worker":
        figures.update(worker_lost(seen, killed_at, before_steps=steps))
    if service == "dashboard":
        wait_for(lambda: urllib.request.urlopen(f"http://127.0.0.1:{dashboard}/healthz", timeout=2).status == 200,
                 60, "the restarted dashboard's page", tolerate=(OSError,))
    if service in OWN_PROGRESS:
        wait_for(lambda: seen.rising(service, OWN_PROGRESS[service], killed_at), 120, f"{name}'s own progress after the restart")
    wait_for(lambda: seen.rising("env-worker", "env_steps", killed_at), 120, "env steps after the kill")
    wait_for(lambda: seen.rising("dynamics-learner", "updates", killed_at), 120, "learner updates after the kill")
    report = wait_for(lambda: [r for r in seen.reports_after(killed_at) if r.weights_version > version], 180,
                      "a graph report from weights newer than the kill")[0]
    figures["run_recovered_s"] = round(time.time() - killed_at, 1)
    figures["report_weights_version"] = report.weights_version
    figures["learner_counted_lost_steps"] = int(seen.latest("dynamics-learner", "lost_steps") - lost)
    return figures


def learner_resumed(seen: Seen, first: ServiceStats, killed_at: float, updates: float, version: float) -> dict[str, Any]:
    """The restarted learner resumed from its checkpoint: a positive update count no higher than the
    killed one's, versions above any it published; the transitions it lost are those published
    before the kill that its checkpoint did not hold."""
    resumed = first.values["resumed_at_update"]
    assert 0 < resumed <= updates, (resumed, updates)
    assert first.values["weights_version"] >= version, "weights versions went backwards after the restart"
    published = seen.published(killed_at)
    return {"resumed_at_update": int(resumed), "updates_at_kill": int(updates),
            "weights_version_at_kill": int(version), "first_version_after": int(first.values["weights_version"]),
            "transitions_lost": int(published - first.values["resumed_env_steps"])}


def worker_lost(seen: Seen, killed_at: float, before_steps: float) -> dict[str, Any]:
    """What a killed worker lost: steps it reported stepping that never arrived (its unfinished batch);
    its next life draws new episode ids (generation 1)."""
    old = sum(n for t, n, g in seen.batches if g == 0)
    wait_for(lambda: any(g == 1 for _, _, g in seen.batches), 120, "a batch from the restarted worker")
    assert not any(g == 0 and t > killed_at + 1.0 for t, _, g in seen.batches), "the old life's episodes came back"
    lost = max(0, int(before_steps) - old)
    assert lost < BATCH_STEPS, (before_steps, old)
    return {"transitions_lost_at_least": lost, "bound": f"< one batch ({BATCH_STEPS} steps)"}
