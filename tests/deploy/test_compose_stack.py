"""The compose stack built and run for real (``make test-compose``; ``.ci/run`` runs it after ``make test``).

A private dockerd (tests/deploy/engine.py), local stand-ins for the images no registry serves here and
the project image from ``deploy/Dockerfile`` (tests/deploy/standins.py), then the shipped
``compose.yaml`` with the smallest override (``tests/deploy/compose.smoke.yaml``: the router and
Grafana). The tests run in file order against one stack: healthy, data flowing, scraped, scaled with
``make scale``, a killed learner resuming from its checkpoint, ``causeway stop``, ``make down``.
Measured figures go to ``test-artifacts/compose/figures.json``. Skipped, saying why, only where no
Docker engine can start.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
import urllib.parse
import urllib.request
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, TypeVar

import pytest

from services.bus.router import free_tcp_port
from tests.deploy import REPO, engine, standins

pytestmark = [pytest.mark.slow, pytest.mark.integration, pytest.mark.timeout(3600)]

ARTIFACTS = REPO / "test-artifacts" / "compose"
OVERRIDE = "tests/deploy/compose.smoke.yaml"
RUN_ID = "compose"
CAUSEWAY = str(REPO / ".venv" / "bin" / "causeway")
SERVICES = ("router", "env-worker", "dynamics-learner", "graph-evaluator", "dashboard", "prometheus")
CAUSEWAY_SERVICES = ("env-worker", "dynamics-learner", "graph-evaluator", "dashboard")
WORKER_STEPS_PER_SECOND = 500
"""Each env-worker's throttle here (2,000 by default): three of them still fit on two shared cores
beside the learner, so the rate can be seen to rise (at 2,000 it rose 2,099 -> 2,327 steps/s)."""
T = TypeVar("T")


def compose_command() -> list[str]:
    """``docker compose`` (v2) where the CLI has it, else ``docker-compose`` (1.29), as the Makefile does."""
    if subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    return ["docker-compose"]


@dataclass
class Stack:
    """One compose project on the private engine, with its host ports on loopback."""

    engine: engine.Engine
    project: str
    ports: dict[str, int]
    figures: dict[str, Any] = field(default_factory=dict)
    down: bool = False

    def environ(self) -> dict[str, str]:
        env = {k: v for k, v in self.engine.environ().items() if not k.startswith(("CAUSEWAY_", "ZENOH_"))}
        env.update(COMPOSE_FILE=os.pathsep.join(["compose.yaml", OVERRIDE]), COMPOSE_PROJECT_NAME=self.project,
                   ROUTER_PORT=str(self.ports["router"]), DASHBOARD_PORT=str(self.ports["dashboard"]),
                   PROMETHEUS_PORT=str(self.ports["prometheus"]), GRAFANA_PORT=str(self.ports["grafana"]),
                   CAUSEWAY_MAX_STEPS_PER_SECOND=str(WORKER_STEPS_PER_SECOND))
        return env

    def run(self, command: list[str], timeout: float = 300, check: bool = True) -> subprocess.CompletedProcess:
        result = subprocess.run(command, cwd=REPO, env=self.environ(), capture_output=True, text=True,
                                timeout=timeout)
        if check:
            assert result.returncode == 0, f"{' '.join(command)}: {result.stdout[-2000:]}{result.stderr[-3000:]}"
        return result

    def compose(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        return self.run([*compose_command(), *args], timeout=timeout)

    def make(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        return self.run(["make", "--no-print-directory", *args], timeout=timeout)

    def containers(self) -> list[dict[str, Any]]:
        """The project's containers: service, name, state, health, exit code, restarts, pid."""
        ids = self.engine.docker("ps", "-aq", "--filter", f"label=com.docker.compose.project={self.project}",
                                 ).stdout.decode().split()
        if not ids:
            return []
        inspected = json.loads(self.engine.docker("inspect", *ids).stdout)
        return [{"service": c["Config"]["Labels"].get("com.docker.compose.service"), "name": c["Name"].lstrip("/"),
                 "id": c["Id"], "state": c["State"]["Status"], "exit_code": c["State"]["ExitCode"],
                 "health": (c["State"].get("Health") or {}).get("Status"), "restarts": c["RestartCount"],
                 "pid": c["State"]["Pid"], "started_at": c["State"]["StartedAt"]} for c in inspected]

    def container(self, service: str) -> dict[str, Any]:
        found = [c for c in self.containers() if c["service"] == service]
        assert len(found) == 1, found
        return found[0]

    def prometheus(self, path: str, **params: str) -> Any:
        url = f"http://127.0.0.1:{self.ports['prometheus']}{path}?{urllib.parse.urlencode(params)}"
        with urllib.request.urlopen(url, timeout=10) as response:
            body = json.loads(response.read())
        assert body["status"] == "success", body
        return body["data"]

    def query(self, expr: str) -> dict[str, float]:
        """An instant PromQL query: instance (or job) -> value."""
        result = self.prometheus("/api/v1/query", query=expr)["result"]
        return {r["metric"].get("instance", r["metric"].get("job", "")): float(r["value"][1]) for r in result}

    def targets(self) -> list[dict[str, Any]]:
        return self.prometheus("/api/v1/targets", state="active")["activeTargets"]

    def status(self, listen_s: float = 4.0) -> dict[str, Any]:
        """``causeway status --json`` through the router's published port, as an operator runs it."""
        result = self.run([CAUSEWAY, "status", "--run", RUN_ID, "--connect", f"tcp/127.0.0.1:{self.ports['router']}",
                           "--listen-s", str(listen_s), "--json"], timeout=60)
        return json.loads(result.stdout)

    def save_logs(self) -> None:
        logs = self.run([*compose_command(), "logs", "--no-color", "--timestamps"], timeout=120, check=False)
        (ARTIFACTS / "stack.log").write_text(logs.stdout + logs.stderr)


def wait_for(what: str, probe: Callable[[], T], done: Callable[[T], bool], timeout_s: float,
             interval_s: float = 2.0) -> T:
    """Poll ``probe`` until ``done`` holds; fail with the last value after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    value: Any = None
    while True:
        try:
            value = probe()
            if done(value):
                return value
        except (OSError, AssertionError, KeyError, ValueError, subprocess.SubprocessError) as exc:
            value = exc
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s:.0f} s; last: {value!r}"[:4000])
        time.sleep(interval_s)


def _stack_in_engine(eng: engine.Engine) -> Stack:
    ports = {name: free_tcp_port() for name in ("router", "dashboard", "prometheus", "grafana")}
    return Stack(eng, f"causewaysmoke{os.getpid()}", ports)


@pytest.fixture(scope="module")
def stack() -> Iterator[Stack]:
    if shutil.which("docker-compose") is None and shutil.which("docker") is None:
        pytest.skip("no docker/docker-compose (make sysdeps-compose installs them)")
    shutil.rmtree(ARTIFACTS, ignore_errors=True)
    ARTIFACTS.mkdir(parents=True)
    try:
        eng = engine.start()
    except engine.EngineUnavailable as exc:
        pytest.skip(f"no Docker engine can start here: {exc}")
    the_stack = _stack_in_engine(eng)
    try:
        times = standins.BuildTimes()
        standins.ensure_base_images(eng, ARTIFACTS / "build.log", times)
        standins.build_project_image(eng, ARTIFACTS / "build.log", times)
        the_stack.figures["build"] = vars(times)
        size = eng.docker("image", "inspect", "-f", "{{.Size}}", standins.PROJECT_IMAGE).stdout.decode()
        the_stack.figures["image_size_mb"] = round(int(size) / 1e6)
        yield the_stack
    finally:
        if not the_stack.down:
            the_stack.save_logs()
            the_stack.run([*compose_command(), "down", "-v", "--remove-orphans", "--timeout", "20"], check=False)
        shutil.copy(eng.log_path, ARTIFACTS / "dockerd.log")
        engine.stop(eng)
        (ARTIFACTS / "figures.json").write_text(json.dumps(the_stack.figures, indent=1) + "\n")


def test_every_service_becomes_healthy(stack: Stack) -> None:
    started = time.monotonic()
    stack.compose("up", "-d", timeout=600)
    healthy = wait_for("every service healthy", stack.containers,
                       lambda cs: {c["service"] for c in cs if c["health"] == "healthy"} >= set(SERVICES), 300)
    stack.figures["seconds_to_all_healthy"] = round(time.monotonic() - started, 1)
    assert {c["service"] for c in healthy} == set(SERVICES), "grafana (no image here) must not start"
    assert all(c["state"] == "running" and c["restarts"] == 0 for c in healthy), healthy


def test_transitions_flow_and_graph_reports_are_published(stack: Stack) -> None:
    def counters() -> dict[str, float]:
        return {name: sum(stack.query(f"{name}").values()) for name in (
            "causeway_transition_batches_published_total", "causeway_dynamics_updates_total",
            "causeway_graph_reports_total")}
    values = wait_for("transitions published, learner updating, graph reports published", counters,
                      lambda v: all(x > 0 for x in v.values()), 420, interval_s=5)
    received = stack.query('causeway_messages_received_total{job="dynamics-learner"}')
    assert sum(received.values()) > 0
    stack.figures["first_counters"] = values


def test_prometheus_scrapes_every_target_and_serves_graph_f1(stack: Stack) -> None:
    targets = wait_for("every target up", stack.targets, lambda ts: {t["labels"]["job"] for t in ts if
                       t["health"] == "up"} >= set(CAUSEWAY_SERVICES) and all(t["health"] == "up" for t in ts), 60)
    assert {t["labels"]["job"] for t in targets} == set(CAUSEWAY_SERVICES), "policy profile off: no such targets"
    f1 = wait_for("causeway_graph_f1_ratio", lambda: stack.query("causeway_graph_f1_ratio"), bool, 60)
    assert all(0.0 <= v <= 1.0 for v in f1.values()), f1
    stack.figures["graph_f1_ratio"] = max(f1.values())


def _env_step_rate(stack: Stack) -> tuple[float, float]:
    """Total env steps/s: from Prometheus (rate over 30 s) and from ``causeway status``."""
    prometheus = sum(stack.query("rate(causeway_env_steps_total[30s])").values())
    status = stack.status(listen_s=6.0)
    return prometheus, float(status["totals"].get("env-worker", {}).get("rate", 0.0))


def test_make_scale_gives_three_env_workers_seen_by_prometheus_and_status(stack: Stack) -> None:
    one = _env_step_rate(stack)
    stack.make("scale", "N=3")
    workers = [c for c in stack.containers() if c["service"] == "env-worker"]
    assert len(workers) == 3 and all(c["state"] == "running" for c in workers), workers
    wait_for("three env-worker targets up", stack.targets,
             lambda ts: len([t for t in ts if t["labels"]["job"] == "env-worker" and t["health"] == "up"]) == 3, 90)
    status = wait_for("three env-workers in causeway status", stack.status,
                      lambda s: s["totals"].get("env-worker", {}).get("alive") == 3, 60)
    names = {row["instance"] for row in status["services"] if row["service"] == "env-worker" and row["token"]}
    assert len(names) == 3, names
    time.sleep(35)  # a full rate window with three workers
    three = _env_step_rate(stack)
    stack.figures["env_steps_per_second"] = {"one_worker": {"prometheus": round(one[0]), "status": round(one[1])},
                                             "three_workers": {"prometheus": round(three[0]), "status": round(three[1])}}
    assert three[0] > 1.5 * one[0] and three[1] > 1.5 * one[1], stack.figures["env_steps_per_second"]


def _learner_updates(stack: Stack) -> float:
    rows = [r for r in stack.status()["services"] if r["service"] == "dynamics-learner" and r["token"]]
    assert len(rows) == 1 and "updates" in rows[0]["values"], rows
    return rows[0]["values"]["updates"]


def test_killed_learner_resumes_from_its_checkpoint(stack: Stack) -> None:
    before = _learner_updates(stack)
    assert before > 0
    stack.run([CAUSEWAY, "checkpoint", "--run", RUN_ID, "--connect", f"tcp/127.0.0.1:{stack.ports['router']}"])
    wait_for("the learner's checkpoint", lambda: stack.query('causeway_checkpoints_total{job="dynamics-learner"}'),
             lambda v: sum(v.values()) >= 1, 60)
    time.sleep(3)
    learner = stack.container("dynamics-learner")
    stack.engine.docker("kill", learner["id"])
    time.sleep(5)
    killed = stack.container("dynamics-learner")
    assert (killed["state"], killed["exit_code"]) == ("exited", 137), killed  # a manual stop: not restarted
    stack.compose("up", "-d")  # what an operator types; starts the stopped service again
    after = wait_for("the learner back with its updates", lambda: _learner_updates(stack), lambda u: u > 0, 180)
    stack.figures["learner_updates"] = {"before_kill": before, "first_beat_after_restart": after}
    assert after >= before, stack.figures["learner_updates"]

    # A crash (the process killed from outside Docker) is restarted by the policy, also from the checkpoint.
    learner = stack.container("dynamics-learner")
    crashed_at = _learner_updates(stack)
    os.kill(learner["pid"], signal.SIGKILL)
    restarted = wait_for("the crashed learner restarted by Docker", lambda: stack.container("dynamics-learner"),
                         lambda c: c["restarts"] >= 1 and c["state"] == "running", 120)
    again = wait_for("the restarted learner's updates", lambda: _learner_updates(stack), lambda u: u > 0, 180)
    stack.figures["learner_updates"].update(before_crash=crashed_at, after_crash_restart=again,
                                            docker_restarts=restarted["restarts"])
    assert again > 0.5 * crashed_at, stack.figures["learner_updates"]


def test_causeway_stop_over_the_bus_stops_the_services_cleanly(stack: Stack) -> None:
    result = stack.run([CAUSEWAY, "stop", "--run", RUN_ID, "--connect", f"tcp/127.0.0.1:{stack.ports['router']}",
                        "--timeout-s", "60"], timeout=120)
    assert "stopped:" in result.stdout, result.stdout
    stopped = wait_for("every causeway service exited", stack.containers, lambda cs: all(
        c["state"] == "exited" for c in cs if c["service"] in CAUSEWAY_SERVICES), 60)
    time.sleep(10)  # the restart policy (on-failure) must leave a clean exit alone
    for c in stack.containers():
        if c["service"] in CAUSEWAY_SERVICES:
            assert (c["state"], c["exit_code"]) == ("exited", 0), c
    stack.figures["stopped"] = sorted(c["name"] for c in stopped if c["service"] in CAUSEWAY_SERVICES)


def test_make_down_leaves_no_container_and_no_network(stack: Stack) -> None:
    stack.save_logs()
    stack.make("down", timeout=300)
    stack.down = True
    assert stack.engine.docker("ps", "-aq").stdout.decode().split() == []
    networks = stack.engine.docker("network", "ls", "--format", "{{.Name}}").stdout.decode().split()
    assert sorted(networks) == ["host", "none"], networks
