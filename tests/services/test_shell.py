"""The service shell's helpers every service loop uses: the checkpoint when due, the decoded query, the
wait for the EnvSpec that a stop ends."""
from __future__ import annotations

import threading
import time
from pathlib import Path

from proto import topics
from proto.codec import encode
from proto.messages import Control, ServiceStats
from services.bus.memory import InMemoryBus, InMemoryTransport
from services.runtime.config import ServiceConfig
from services.runtime.shell import ServiceShell


class _Core:
    def __init__(self) -> None:
        self.written: list[Path] = []

    def checkpoint(self, path: Path) -> None:
        self.written.append(path)


class _Counter:
    def __init__(self) -> None:
        self.value = 0

    def inc(self) -> None:
        self.value += 1


def _shell(bus: InMemoryBus, every_s: float = 30.0) -> ServiceShell:
    return ServiceShell("graph-evaluator", ServiceConfig(run_id="shell", checkpoint_every_s=every_s),
                        InMemoryTransport(bus))


def test_a_checkpoint_is_written_when_asked_for_or_due_and_not_before(tmp_path: Path) -> None:
    bus, core, counter = InMemoryBus(), _Core(), _Counter()
    shell = _shell(bus, every_s=30.0)
    try:
        start = time.monotonic()
        assert shell.checkpoint_if_due(core, tmp_path / "c.pt", start, counter) == start
        assert core.written == [] and counter.value == 0
        operator = InMemoryTransport(bus)
        operator.publish(topics.control("shell", "graph-evaluator"), encode(Control("checkpoint", issued_at=time.time())))
        shell.poll_control()
        assert shell.checkpoint_requested
        asked = shell.checkpoint_if_due(core, tmp_path / "c.pt", start, counter)
        assert asked >= start and core.written == [tmp_path / "c.pt"] and counter.value == 1
        assert not shell.checkpoint_requested
        due = shell.checkpoint_if_due(core, tmp_path / "c.pt", asked - 31.0)
        assert due >= asked and len(core.written) == 2 and counter.value == 1, "no counter given: none counted"
    finally:
        shell.close()


def test_a_query_decodes_the_answers_and_counts_one_off_the_contract() -> None:
    bus = InMemoryBus()
    shell = _shell(bus)
    server = InMemoryTransport(bus)
    try:
        good = ServiceStats(service="x", instance="0", values={"a": 1.0}, timestamp=1.0)
        latest = server.serve_latest("causeway/shell/probe/good")
        latest.set(encode(good))
        bad = server.serve_latest("causeway/shell/probe/bad")
        bad.set(b"not msgpack of a ServiceStats")
        assert shell.query("causeway/shell/probe/good", ServiceStats) == [good]
        assert shell.metrics.rejected_count == 0
        assert shell.query("causeway/shell/probe/bad", ServiceStats) == []
        assert shell.metrics.rejected_count == 1
    finally:
        shell.close()
        server.close()


def test_a_stop_ends_the_wait_for_a_spec_nobody_serves() -> None:
    """A run stopped before its spec came (a frames run stopped before the slots froze) once left the
    waiting service querying forever: the wait must apply control commands."""
    bus = InMemoryBus()
    shell = _shell(bus)
    operator = InMemoryTransport(bus)
    stop = threading.Timer(0.3, lambda: operator.publish(topics.control("shell", "all"),
                                                          encode(Control("stop", issued_at=time.time()))))
    try:
        stop.start()
        start = time.monotonic()
        assert shell.wait_for_spec(poll_s=0.05) is None
        assert shell.stopping.is_set() and time.monotonic() - start < 10.0
    finally:
        stop.cancel()
        shell.close()
