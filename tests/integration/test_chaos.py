"""Chaos (issue 20, item 4): SIGKILL each kind of service mid-run, then the supervisor itself.

A real ``causeway run`` (router, supervisor and every service as processes on loopback; CDL on
Chemical, PPO with the prediction-difference intrinsic reward, so all six kinds of service run). Each
kind is killed in turn; the supervisor must restart it, the run must go on (env steps, learner
updates and graph reports keep coming), a restarted learner must resume from its checkpoint with
versions above any it published and its update count not overcounted, and the run must end with a
summary. The supervisor killed: every service dies with it (PR_SET_PDEATHSIG), nothing is left, and
the same command on the same run directory resumes. A stalled learner (SIGSTOP) stalls nothing else
and its memory stays bounded. Recovery times and transitions lost are written to
``test-artifacts/chaos/`` (the table in docs/operating.md).
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

import pytest

from proto import topics
from proto.codec import ProtocolError, decode
from proto.messages import GraphReport, ServiceStats, TransitionBatch
from services.bus.credentials import read_credentials, role_file
from services.bus.router import free_tcp_port
from services.bus.zenoh_transport import ZenohTransport
from services.env_worker.core import GENERATION_EPISODES
from tests import waiting

pytestmark = [pytest.mark.integration, pytest.mark.slow]
REPO = Path(__file__).resolve().parents[2]
ARTIFACTS = REPO / "test-artifacts" / "chaos"
KINDS = ("env-worker-0", "dynamics-learner", "graph-evaluator", "intrinsic-reward", "policy-learner", "dashboard")
"""Process names in processes.json, killed in this order."""
OWN_PROGRESS = {"env-worker": "env_steps", "dynamics-learner": "updates", "graph-evaluator": "reports",
                "intrinsic-reward": "scored_batches", "policy-learner": "env_steps"}
"""The counter in each service's stats beat that shows it working again (the dashboard: its page)."""
BATCH_STEPS = 256
wait_for = waiting.wait_for


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
            self.batches.append((time.time(), len(batch), int(batch.episode_id.min()) // GENERATION_EPISODES))

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


def command(run_dir: Path, port: int, metrics: int, dashboard: int, policy: bool = True) -> list[str]:
    cmd = [sys.executable, "-m", "services.cli", "run", "--graph", "collider", "--num-objects", "3",
           "--max-seconds", "900", "--router-port", str(port), "--metrics-base-port", str(metrics),
           "--run-dir", str(run_dir), "--checkpoint-every-s", "2", "--evaluator-min-interval-s", "1",
           "--learner-publish-every-s", "1", "--progress", "false", "--worker-max-steps-per-second", "500",
           "--worker-batch-steps", str(BATCH_STEPS), "--dashboard-port", str(dashboard), "--evaluate", "false",
           "--seed", "3"]
    return cmd + (["--collector", "ppo", "--intrinsic", "preddiff"] if policy else [])


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


def kill_and_recover(bus: Bus, run_dir: Path, name: str, dashboard: int) -> dict[str, Any]:
    """SIGKILL ``name``; wait for its restart and for the run to move on. Returns the figures."""
    seen, service = bus.seen, name.rsplit("-", 1)[0] if name.startswith("env-worker") else name
    before = table(run_dir)["processes"][name]
    steps, updates = seen.latest("env-worker", "env_steps"), seen.latest("dynamics-learner", "updates")
    version = seen.latest("dynamics-learner", "weights_version")
    killed_at = time.time()
    os.kill(before["pid"], signal.SIGKILL)
    wait_for(lambda: table(run_dir)["processes"][name]["pid"] != before["pid"], 60, f"{name}'s restart")
    first = wait_for(lambda: seen.of(service, after=killed_at + 0.5), 120, f"a beat from the restarted {name}")[0]
    figures: dict[str, Any] = {"service": name, "restarts": table(run_dir)["processes"][name]["restarts"],
                               "back_on_bus_s": round(first.timestamp - killed_at, 1)}
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


def test_each_service_killed_in_turn_is_restarted_and_the_run_goes_on(tmp_path: Path) -> None:
    run_dir, port, dashboard = tmp_path / "run", free_tcp_port(), free_tcp_port()
    metrics = 21000 + (os.getpid() % 1500) * 20
    stack = start(command(run_dir, port, metrics, dashboard))
    bus, figures = None, []
    try:
        wait_for(lambda: set(KINDS) <= set(table(run_dir).get("processes", {})), 90, "every service started")
        bus = Bus(f"tcp/127.0.0.1:{port}", run_dir, "run")
        wait_for(lambda: bus.seen.reports and all(bus.seen.of(k.rsplit("-", 1)[0] if k.startswith("env-") else k) for k in KINDS),
                 240, "a graph report and a beat from every service")
        wait_for(lambda: (run_dir / "checkpoints" / "dynamics-learner-0.pt").exists(), 60, "a learner checkpoint")
        for name in KINDS:
            figures.append(kill_and_recover(bus, run_dir, name, dashboard))
        max_updates = max(b.values.get("updates", 0) for b in bus.seen.of("dynamics-learner"))
    finally:
        out = stop(stack, run_dir)
        if bus is not None:
            bus.close()
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "figures.json").write_text(json.dumps({"kills": figures}, indent=1))
        print(json.dumps(figures, indent=1))
    assert stack.returncode == 0, out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts"] == len(KINDS)
    assert 0 < summary["updates"] <= max_updates + 50, (summary["updates"], max_updates)  # not the lives summed
    assert summary["env_steps"] > 0 and summary["f1"] >= 0.0


def test_a_killed_supervisor_takes_its_services_with_it_and_the_run_resumes(tmp_path: Path) -> None:
    run_dir, port, dashboard = tmp_path / "run", free_tcp_port(), free_tcp_port()
    metrics = 23000 + (os.getpid() % 1500) * 20
    cmd = command(run_dir, port, metrics, dashboard, policy=False)
    stack = start(cmd)
    try:
        wait_for(lambda: (run_dir / "checkpoints" / "dynamics-learner-0.pt").exists(), 180, "a learner checkpoint")
        services = {name: e["pid"] for name, e in table(run_dir)["processes"].items()}
        assert table(run_dir)["supervisor_pid"] == stack.pid
        killed_at = time.monotonic()
        stack.send_signal(signal.SIGKILL)
        stack.wait(30)
        wait_for(lambda: not any(pid_alive(p) for p in services.values()), 60, "every service to die with the supervisor")
        gone_s = time.monotonic() - killed_at
    finally:
        stop(stack, run_dir, timeout=30)
    again = start(cmd)
    try:
        wait_for(lambda: again.poll() is not None or table(run_dir).get("supervisor_pid") == again.pid, 90,
                 "the second supervisor's process table")
        assert again.poll() is None, again.communicate()[0]
        bus = Bus(f"tcp/127.0.0.1:{port}", run_dir, "run")
        resumed = wait_for(lambda: [b for b in bus.seen.of("dynamics-learner") if b.values.get("resumed_at_update", 0) > 0],
                           180, "the learner resumed from its checkpoint")[0]
        bus.close()
    finally:
        out = stop(again, run_dir)
    assert again.returncode == 0, out
    assert (run_dir / "summary.json").exists()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "supervisor.json").write_text(json.dumps(
        {"services_gone_s": round(gone_s, 1), "resumed_at_update": resumed.values["resumed_at_update"]}))
    print(f"services gone {gone_s:.1f} s after the supervisor's SIGKILL; resumed at update "
          f"{resumed.values['resumed_at_update']:.0f}")


def rss_mib(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line for line in status.splitlines() if line.startswith("VmRSS")).split()[1]) // 1024


def test_a_stalled_learner_stalls_nothing_else_and_its_memory_stays_bounded(tmp_path: Path) -> None:
    """The learner SIGSTOPped for 20 s under an unthrottled worker: the worker keeps stepping (its
    publications do not block on the stalled subscriber), the learner's memory does not grow with the
    backlog (its inbox is bounded; what overflows is dropped and counted), and it trains again at once."""
    run_dir, port, dashboard = tmp_path / "run", free_tcp_port(), free_tcp_port()
    metrics = 25000 + (os.getpid() % 1500) * 20
    cmd = command(run_dir, port, metrics, dashboard, policy=False)
    cmd[cmd.index("--worker-max-steps-per-second") + 1] = "0"
    stack = start(cmd)
    bus = None
    try:
        wait_for(lambda: "dynamics-learner" in table(run_dir).get("processes", {}), 90, "the learner started")
        bus = Bus(f"tcp/127.0.0.1:{port}", run_dir, "run")
        wait_for(lambda: bus.seen.reports, 240, "a graph report")
        pid = table(run_dir)["processes"]["dynamics-learner"]["pid"]
        steps, before = bus.seen.latest("env-worker", "env_steps"), rss_mib(pid)
        os.kill(pid, signal.SIGSTOP)
        stopped_at = time.time()
        try:
            wait_for(lambda: time.time() - stopped_at > 20 and bus.seen.latest("env-worker", "env_steps") > steps + 10_000,
                     60, "the worker stepping on while the learner is stopped")
            stepped = bus.seen.latest("env-worker", "env_steps") - steps
        finally:
            os.kill(pid, signal.SIGCONT)
        resumed_at = time.time()
        wait_for(lambda: bus.seen.rising("dynamics-learner", "updates", resumed_at), 120, "the learner training again")
        back_s = time.time() - resumed_at
        time.sleep(5)  # the backlog it was sent, drained
        after = rss_mib(pid)
        body = urllib.request.urlopen(f"http://127.0.0.1:{metrics + 1}/metrics", timeout=5).read().decode()
        drops = sum(float(line.rsplit(" ", 1)[1]) for line in body.splitlines()
                    if line.startswith('causeway_messages_dropped_total{reason="transitions_'))
        assert table(run_dir)["processes"]["dynamics-learner"]["restarts"] == 0
        assert after - before < 150, (before, after)
    finally:
        if bus is not None:
            bus.close()
        out = stop(stack, run_dir)
    assert stack.returncode == 0, out
    figures = {"stalled_s": 20, "worker_steps_meanwhile": int(stepped), "learner_rss_mib": [before, after],
               "learner_training_again_s": round(back_s, 1), "transitions_batches_dropped_counted": int(drops)}
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "stall.json").write_text(json.dumps(figures))
    print(json.dumps(figures))
