"""``causeway scale | stop | checkpoint`` on the in-memory bus against a fake supervisor, and ``--run-dir``."""
from __future__ import annotations

import argparse
import io
import json
import threading
from pathlib import Path
from typing import Iterator

import pytest

from proto import topics
from proto.codec import decode
from proto.messages import Control
from services.bus import Handle, InMemoryBus, InMemoryTransport
from services.ops import control
from services.ops.target import OpsError, Target, read_run_dir, resolve_target

RUN = "r1"


class FakeSupervisor:
    """Holds one env-worker token per instance and applies scale/stop like the real supervisor, a bit later."""

    def __init__(self, bus: InMemoryBus, workers: int, delay_s: float = 0.05) -> None:
        self.transport = InMemoryTransport(bus)
        self.delay_s = delay_s
        self.received: list[tuple[str, Control]] = []
        self.tokens: dict[tuple[str, int], Handle] = {}
        self.other = [self.transport.declare_token(topics.alive(RUN, name, "0"))
                      for name in ("dynamics-learner", "graph-evaluator")]
        for i in range(workers):
            self.tokens[("env-worker", i)] = self.transport.declare_token(topics.alive(RUN, "env-worker", str(i)))
        for target in ("supervisor", "all"):
            self.transport.subscribe(topics.control(RUN, target), self.on_control)

    def on_control(self, key: str, payload: bytes) -> None:
        command = decode(payload, Control)
        self.received.append((key, command))
        action = {"scale": lambda: self.scale(int(command.argument.partition("=")[2])), "stop": self.stop}
        if command.command in action:
            threading.Timer(self.delay_s, action[command.command]).start()

    def scale(self, count: int) -> None:
        current = sorted(i for _, i in self.tokens)
        for i in range(max(current, default=-1) + 1, max(current, default=-1) + 1 + count - len(current)):
            self.tokens[("env-worker", i)] = self.transport.declare_token(topics.alive(RUN, "env-worker", str(i)))
        for i in sorted(current, reverse=True)[: max(len(current) - count, 0)]:
            self.tokens.pop(("env-worker", i)).close()

    def stop(self) -> None:
        for handle in list(self.tokens.values()) + self.other:
            handle.close()
        self.tokens.clear()


@pytest.fixture
def bus() -> InMemoryBus:
    return InMemoryBus()


@pytest.fixture
def operator(bus: InMemoryBus) -> Iterator[InMemoryTransport]:
    transport = InMemoryTransport(bus)
    yield transport
    transport.close()


def test_scale_up_asks_the_supervisor_and_waits_for_the_tokens(bus: InMemoryBus, operator: InMemoryTransport) -> None:
    supervisor, out = FakeSupervisor(bus, workers=1), io.StringIO()

    assert control.scale_local(operator, RUN, "env-worker", 3, timeout_s=2.0, out=out) == 0

    ((key, command),) = supervisor.received
    assert key == topics.control(RUN, "supervisor") and (command.command, command.argument) == ("scale", "env-worker=3")
    assert command.issued_at > 0
    assert "env-worker: 1 -> 3 alive" in out.getvalue() and "started: env-worker/1, env-worker/2" in out.getvalue()


def test_scale_down_reports_the_stopped_instances(bus: InMemoryBus, operator: InMemoryTransport) -> None:
    FakeSupervisor(bus, workers=3)
    out = io.StringIO()
    assert control.scale_local(operator, RUN, "env-worker", 1, timeout_s=2.0, out=out) == 0
    assert "3 -> 1 alive" in out.getvalue() and "stopped: env-worker/1, env-worker/2" in out.getvalue()


def test_scale_without_a_supervisor_is_not_confirmed(operator: InMemoryTransport) -> None:
    with pytest.raises(OpsError, match="still 0 alive .* is the run's supervisor up") as raised:
        control.scale_local(operator, RUN, "env-worker", 2, timeout_s=0.2, out=io.StringIO())
    assert raised.value.exit_code == 1


@pytest.mark.parametrize("service,count", [("dynamics-learner", 2), ("graph-evaluator", 1), ("env-worker", -1)])
def test_scale_main_refuses_what_cannot_scale(service: str, count: int) -> None:
    with pytest.raises(OpsError) as raised:
        control.scale_main([service, str(count), "--run", RUN])
    assert raised.value.exit_code == 2


def test_stop_goes_to_all_and_waits_for_every_token(bus: InMemoryBus, operator: InMemoryTransport) -> None:
    supervisor, out = FakeSupervisor(bus, workers=2), io.StringIO()

    assert control.stop(operator, RUN, timeout_s=2.0, out=out) == 0
    assert [(k, c.command) for k, c in supervisor.received] == [(topics.control(RUN, "all"), "stop")]
    assert "stopped: dynamics-learner/0, env-worker/0, env-worker/1, graph-evaluator/0" in out.getvalue()
    assert operator.alive(topics.alive(RUN)) == []


def test_checkpoint_reports_who_was_alive(bus: InMemoryBus, operator: InMemoryTransport) -> None:
    supervisor, out = FakeSupervisor(bus, workers=1), io.StringIO()

    assert control.checkpoint(operator, RUN, out) == 0
    assert [(k, c.command) for k, c in supervisor.received] == [(topics.control(RUN, "all"), "checkpoint")]
    assert "alive to receive it: dynamics-learner/0, env-worker/0, graph-evaluator/0" in out.getvalue()


def test_checkpoint_with_nobody_alive_is_exit_1(operator: InMemoryTransport) -> None:
    out = io.StringIO()
    assert control.checkpoint(operator, RUN, out) == 1
    assert "alive to receive it: none" in out.getvalue()


def _args(**flags: str | None) -> argparse.Namespace:
    return argparse.Namespace(**{"connect": None, "run_id": None, "run_dir": None, **flags})


def test_run_dir_gives_router_and_run_id(tmp_path: Path) -> None:
    (tmp_path / "config.json").write_text(json.dumps({"run_id": "chem-1", "router_port": 7555}))
    assert read_run_dir(tmp_path) == Target("tcp/127.0.0.1:7555", "chem-1")
    (tmp_path / "processes.json").write_text(json.dumps({"router": "tcp/127.0.0.1:7666", "processes": {}}))
    assert resolve_target(_args(run_dir=str(tmp_path)), environ={}) == Target("tcp/127.0.0.1:7666", "chem-1")
    assert resolve_target(_args(run_dir=str(tmp_path), connect="tcp/10.0.0.2:7447", run_id="other"),
                          environ={}) == Target("tcp/10.0.0.2:7447", "other")


def test_target_from_flags_and_environment() -> None:
    environ = {"CAUSEWAY_RUN_ID": "compose", "CAUSEWAY_ZENOH_CONNECT": "tcp/127.0.0.1:17447"}
    assert resolve_target(_args(), environ=environ) == Target("tcp/127.0.0.1:17447", "compose")
    assert resolve_target(_args(run_id="x"), environ={}) == Target("tcp/127.0.0.1:7447", "x")


@pytest.mark.parametrize("flags,message", [({}, "which run"), ({"run_id": "a/b"}, "bad run id"),
                                           ({"run_dir": "/nonexistent/run"}, "not a run directory")])
def test_target_errors(flags: dict[str, str], message: str) -> None:
    with pytest.raises(OpsError, match=message):
        resolve_target(_args(**flags), environ={})
