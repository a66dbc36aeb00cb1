"""``ZenohTransport`` against a real router in this process, on loopback, a fresh port per test.

Everything but the key-expression cross-check is ``integration``: real Zenoh sessions, and one
subprocess killed with SIGKILL to show that liveliness reports a dead service.
"""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

import pytest
import zenoh

from services.bus import ZenohTransport, free_tcp_port, key_intersects, start_router, wait_for_router
from tests.bus.test_memory import MakeTransport, TransportContract, eventually

REPO_ROOT = Path(__file__).resolve().parents[2]
integration = pytest.mark.integration


@pytest.fixture
def endpoint() -> Iterator[str]:
    """A router on a fresh loopback port, for this test only."""
    address = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = start_router(address)
    yield address
    router.close()


@pytest.fixture
def make(endpoint: str) -> Iterator[MakeTransport]:
    """Opens clients of this test's router; closes them all afterwards."""
    opened: list[ZenohTransport] = []

    def make() -> ZenohTransport:
        opened.append(ZenohTransport(endpoint))
        return opened[-1]

    yield make
    for transport in opened:
        transport.close()


@integration
class TestZenohContract(TransportContract):
    settle = 0.1


def test_key_intersects_agrees_with_zenoh() -> None:
    chunks = ["a", "b", "*", "**"]
    exprs = ["/".join(p) for n in (1, 2, 3) for p in itertools.product(chunks, repeat=n)]
    for a, b in itertools.product(exprs, repeat=2):
        expected = zenoh.KeyExpr.autocanonize(a).intersects(zenoh.KeyExpr.autocanonize(b))
        assert key_intersects(a, b) == expected, (a, b)


@integration
def test_block_delivers_1000_messages_of_100kb_complete_and_in_order(make: MakeTransport) -> None:
    publisher, subscriber = make(), make()
    received: list[tuple[int, int]] = []
    done = threading.Event()

    def on_message(key: str, payload: bytes) -> None:
        received.append((int.from_bytes(payload[:4], "little"), len(payload)))
        if len(received) == 1000:
            done.set()

    subscriber.subscribe("run/transitions/*", on_message)
    time.sleep(0.1)
    body = bytes(100_000 - 4)
    for seq in range(1000):
        publisher.publish("run/transitions/w0", seq.to_bytes(4, "little") + body, reliable=True)
    assert done.wait(20), f"only {len(received)} of 1000 arrived"
    assert received == [(seq, 100_000) for seq in range(1000)]


@integration
def test_late_joiner_gets_latest_weights_within_one_second(make: MakeTransport) -> None:
    learner = make()
    weights = learner.serve_latest("run/weights/policy")
    for version in range(3):
        weights.set(version.to_bytes(4, "little") + bytes(4_000_000))
    started = time.monotonic()
    late = make()
    replies = late.query("run/weights/policy", timeout=1.0)
    elapsed = time.monotonic() - started
    assert [(k, p[:4], len(p)) for k, p in replies] == [
        ("run/weights/policy", (2).to_bytes(4, "little"), 4_000_004)
    ]
    assert elapsed < 1.0


@integration
@pytest.mark.timeout(30)
def test_sigkilled_process_loses_its_token_within_two_seconds(endpoint: str, make: MakeTransport) -> None:
    watcher, key = make(), "run/alive/env-worker/7"
    seen: list[tuple[str, bool]] = []
    watcher.watch_liveliness("run/alive/**", lambda k, alive: seen.append((k, alive)))
    holder = _start_token_holder(endpoint, key)
    try:
        assert eventually(lambda: seen == [(key, True)], timeout=5.0)
        assert eventually(lambda: watcher.alive("run/alive/**") == [key])
        os.kill(holder.pid, signal.SIGKILL)
        killed = time.monotonic()
        assert eventually(lambda: seen[-1] == (key, False), timeout=2.0)
        print(f"token DELETE {1000 * (time.monotonic() - killed):.1f} ms after SIGKILL")
        assert watcher.alive("run/alive/**") == []
    finally:
        holder.kill()
        holder.wait()


@integration
@pytest.mark.timeout(30)
def test_crashing_process_exits_and_loses_its_token(endpoint: str, make: MakeTransport) -> None:
    watcher, key = make(), "run/alive/policy-learner/0"
    seen: list[tuple[str, bool]] = []
    watcher.watch_liveliness("run/alive/**", lambda k, alive: seen.append((k, alive)))
    holder = _start_token_holder(endpoint, key, "--crash")
    try:
        assert holder.wait(timeout=10) == 1
        assert eventually(lambda: seen[-1:] == [(key, False)])
    finally:
        holder.kill()
        holder.wait()


def _start_token_holder(endpoint: str, key: str, *flags: str) -> subprocess.Popen[str]:
    command = [sys.executable, "-m", "tests.bus.token_holder", endpoint, key, *flags]
    holder = subprocess.Popen(
        command, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    assert holder.stdout is not None and holder.stdout.readline().strip() == "ready"
    return holder


@integration
def test_watcher_declared_late_sees_tokens_already_alive(make: MakeTransport) -> None:
    holders = [make() for _ in range(3)]
    for i, holder in enumerate(holders):
        holder.declare_token(f"run/alive/env/{i}")
    time.sleep(0.1)
    seen: list[tuple[str, bool]] = []
    make().watch_liveliness("run/alive/env/*", lambda k, alive: seen.append((k, alive)))
    assert eventually(lambda: len(seen) == 3)
    assert sorted(seen) == [(f"run/alive/env/{i}", True) for i in range(3)]


@integration
def test_close_is_idempotent_and_handles_survive_it(make: MakeTransport) -> None:
    transport = make()
    handles = [transport.subscribe("k", lambda k, p: None), transport.declare_token("t")]
    latest = transport.serve_latest("v")
    transport.publish("k", b"x")
    transport.close()
    transport.close()
    for handle in handles:
        handle.close()
    latest.close()


@integration
def test_wait_for_router() -> None:
    missing = f"tcp/127.0.0.1:{free_tcp_port()}"
    started = time.monotonic()
    with pytest.raises(TimeoutError):
        wait_for_router(missing, timeout=0.3)
    assert time.monotonic() - started < 2.0
    router = start_router(missing)
    try:
        wait_for_router(missing, timeout=2.0)
    finally:
        router.close()


@integration
def test_throughput_64kb(make: MakeTransport, capsys: pytest.CaptureFixture[str]) -> None:
    publisher, subscriber = make(), make()
    count, size = 2000, 64 * 1024
    done, received = threading.Event(), [0]

    def on_message(key: str, payload: bytes) -> None:
        received[0] += 1
        if received[0] == count:
            done.set()

    subscriber.subscribe("bench/**", on_message)
    time.sleep(0.1)
    payload = bytes(size)
    started = time.perf_counter()
    for _ in range(count):
        publisher.publish("bench/x", payload)
    assert done.wait(30)
    seconds = time.perf_counter() - started
    with capsys.disabled():
        print(f"\nzenoh client->router->client, 64 KB BLOCK: {count * size / seconds / 1e6:.0f} MB/s")
