"""The in-memory bus, and ``TransportContract``: the behaviour every ``Transport`` must show.

``TransportContract`` is a mixin: ``TestInMemoryContract`` here and the Zenoh contract class in
``test_zenoh.py`` run the same tests, each providing a ``make`` fixture that opens transports on
one shared bus. Waits are written as ``eventually`` so the asynchronous transport passes them too.
"""
from __future__ import annotations

import threading
import time
from typing import Callable, Iterator

import pytest

from services.bus import InMemoryBus, InMemoryTransport, Transport, key_intersects

MakeTransport = Callable[[], Transport]


def eventually(predicate: Callable[[], bool], timeout: float = 2.0) -> bool:
    """Poll ``predicate`` until true or ``timeout`` seconds pass; returns its last value."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


class TransportContract:
    """Tests every Transport passes. Subclasses define the ``make`` fixture and ``settle``."""

    settle: float = 0.0
    """Seconds for a declaration to reach the other transports (0 in memory)."""

    def declared(self) -> None:
        time.sleep(self.settle)

    def test_subscriber_gets_matching_keys_only(self, make: MakeTransport) -> None:
        publisher, subscriber = make(), make()
        got: list[tuple[str, bytes]] = []
        subscriber.subscribe("run/transitions/*", lambda k, p: got.append((k, p)))
        self.declared()
        publisher.publish("run/transitions/w0", b"a")
        publisher.publish("run/weights/policy", b"b")
        publisher.publish("run/transitions/w1", b"c")
        assert eventually(lambda: len(got) == 2)
        time.sleep(self.settle)
        assert got == [("run/transitions/w0", b"a"), ("run/transitions/w1", b"c")]

    def test_double_star_matches_any_depth(self, make: MakeTransport) -> None:
        publisher, subscriber = make(), make()
        got: list[str] = []
        subscriber.subscribe("run/**", lambda k, p: got.append(k))
        self.declared()
        for key in ("run/a", "run/a/b/c", "other/a"):
            publisher.publish(key, b"x")
        assert eventually(lambda: sorted(got) == ["run/a", "run/a/b/c"])

    def test_closed_subscription_gets_nothing(self, make: MakeTransport) -> None:
        publisher, subscriber = make(), make()
        got: list[bytes] = []
        handle = subscriber.subscribe("k", lambda k, p: got.append(p))
        self.declared()
        publisher.publish("k", b"1")
        assert eventually(lambda: got == [b"1"])
        handle.close()
        handle.close()
        self.declared()
        publisher.publish("k", b"2")
        time.sleep(self.settle)
        assert got == [b"1"]

    def test_failing_callback_is_logged_and_delivery_goes_on(
        self, make: MakeTransport, caplog: pytest.LogCaptureFixture
    ) -> None:
        publisher, subscriber = make(), make()
        got: list[bytes] = []

        def flaky(key: str, payload: bytes) -> None:
            got.append(payload)
            if payload == b"bad":
                raise ValueError("subscriber bug")

        subscriber.subscribe("k", flaky)
        self.declared()
        for payload in (b"ok", b"bad", b"after"):
            publisher.publish("k", payload)
        assert eventually(lambda: got == [b"ok", b"bad", b"after"])
        assert "subscriber bug" in caplog.text

    def test_query_answers_latest_value_only_once_set(self, make: MakeTransport) -> None:
        server, client = make(), make()
        latest = server.serve_latest("run/weights/policy")
        self.declared()
        assert client.query("run/weights/policy") == []
        latest.set(b"v1")
        latest.set(b"v2")
        assert client.query("run/weights/*") == [("run/weights/policy", b"v2")]
        latest.close()
        self.declared()
        assert client.query("run/weights/*") == []

    def test_query_reaches_every_matching_server(self, make: MakeTransport) -> None:
        first, second, client = make(), make(), make()
        first.serve_latest("run/weights/policy").set(b"p")
        second.serve_latest("run/weights/dynamics").set(b"d")
        self.declared()
        replies = sorted(client.query("run/weights/*"))
        assert replies == [("run/weights/dynamics", b"d"), ("run/weights/policy", b"p")]

    def test_set_also_publishes(self, make: MakeTransport) -> None:
        server, listener = make(), make()
        got: list[bytes] = []
        listener.subscribe("run/weights/policy", lambda k, p: got.append(p))
        latest = server.serve_latest("run/weights/policy")
        self.declared()
        latest.set(b"v1")
        assert eventually(lambda: got == [b"v1"])

    def test_liveliness_reports_existing_then_changes(self, make: MakeTransport) -> None:
        holder, watcher = make(), make()
        holder.declare_token("run/alive/env/0")
        self.declared()
        seen: list[tuple[str, bool]] = []
        watcher.watch_liveliness("run/alive/**", lambda k, a: seen.append((k, a)))
        assert eventually(lambda: seen == [("run/alive/env/0", True)])
        second = holder.declare_token("run/alive/env/1")
        assert eventually(lambda: seen[-1:] == [("run/alive/env/1", True)])
        second.close()
        assert eventually(lambda: seen[-1:] == [("run/alive/env/1", False)])

    def test_alive_lists_tokens(self, make: MakeTransport) -> None:
        holder, observer = make(), make()
        holder.declare_token("run/alive/learner/0")
        holder.declare_token("run/alive/env/0")
        self.declared()
        assert observer.alive("run/alive/**") == ["run/alive/env/0", "run/alive/learner/0"]
        assert observer.alive("run/alive/env/*") == ["run/alive/env/0"]

    def test_closing_a_transport_kills_its_tokens(self, make: MakeTransport) -> None:
        holder, watcher = make(), make()
        holder.declare_token("run/alive/env/0")
        seen: list[bool] = []
        watcher.watch_liveliness("run/alive/**", lambda k, a: seen.append(a))
        assert eventually(lambda: seen == [True])
        holder.close()
        holder.close()
        assert eventually(lambda: seen == [True, False])
        assert watcher.alive("run/alive/**") == []

    def test_closed_transport_refuses_work(self, make: MakeTransport) -> None:
        transport = make()
        transport.close()
        with pytest.raises(RuntimeError):
            transport.publish("k", b"x")
        with pytest.raises(RuntimeError):
            transport.subscribe("k", lambda k, p: None)


class TestInMemoryContract(TransportContract):
    @pytest.fixture
    def make(self) -> Iterator[MakeTransport]:
        bus = InMemoryBus()
        opened: list[InMemoryTransport] = []

        def make() -> Transport:
            opened.append(InMemoryTransport(bus))
            return opened[-1]

        yield make
        for transport in opened:
            transport.close()


@pytest.mark.parametrize(
    ("a", "b", "expected"),
    [
        ("a/b", "a/b", True),
        ("a/b", "a/c", False),
        ("a/*", "a/b", True),
        ("a/*", "a/b/c", False),
        ("a/*", "a", False),
        ("a/**", "a", True),
        ("a/**", "a/b/c", True),
        ("**", "x/y", True),
        ("a/**/c", "a/c", True),
        ("a/**/c", "a/b/d/c", True),
        ("a/**/c", "a/b/d", False),
        ("a/*/c", "a/**", True),
        ("*/b", "a/*", True),
        ("**/z", "a/**", True),
        ("a/*/*", "a/b", False),
    ],
)
def test_key_intersects(a: str, b: str, expected: bool) -> None:
    assert key_intersects(a, b) is expected
    assert key_intersects(b, a) is expected


@pytest.mark.parametrize("bad", ["", "/a", "a/", "a//b"])
def test_invalid_key_expressions_are_rejected(bad: str) -> None:
    with pytest.raises(ValueError):
        key_intersects(bad, "a")


def test_callbacks_run_synchronously_on_the_publisher_thread() -> None:
    bus = InMemoryBus()
    publisher, subscriber = InMemoryTransport(bus), InMemoryTransport(bus)
    threads: list[threading.Thread] = []
    subscriber.subscribe("k", lambda k, p: threads.append(threading.current_thread()))
    publisher.publish("k", b"x")
    assert threads == [threading.current_thread()]


def test_callback_may_publish_without_deadlock() -> None:
    transport = InMemoryTransport()
    got: list[bytes] = []
    transport.subscribe("ping", lambda k, p: transport.publish("pong", p + b"!"))
    transport.subscribe("pong", lambda k, p: got.append(p))
    transport.publish("ping", b"hi")
    assert got == [b"hi!"]


def test_one_subscriber_never_runs_concurrently_with_itself() -> None:
    bus = InMemoryBus()
    subscriber = InMemoryTransport(bus)
    active, overlaps, count = [0], [0], [0]
    guard = threading.Lock()

    def slow(key: str, payload: bytes) -> None:
        with guard:
            active[0] += 1
            overlaps[0] += active[0] > 1
        time.sleep(0.0005)
        with guard:
            active[0] -= 1
            count[0] += 1

    subscriber.subscribe("k", slow)
    publishers = [threading.Thread(target=_publish_many, args=(InMemoryTransport(bus),)) for _ in range(4)]
    for thread in publishers:
        thread.start()
    for thread in publishers:
        thread.join()
    assert count[0] == 4 * 50 and overlaps[0] == 0


def _publish_many(transport: InMemoryTransport) -> None:
    for i in range(50):
        transport.publish("k", i.to_bytes(4, "little"))


def test_tokens_on_one_key_are_counted() -> None:
    bus = InMemoryBus()
    first, second, watcher = InMemoryTransport(bus), InMemoryTransport(bus), InMemoryTransport(bus)
    seen: list[bool] = []
    watcher.watch_liveliness("svc", lambda k, a: seen.append(a))
    first.declare_token("svc")
    second.declare_token("svc")
    first.close()
    assert seen == [True] and watcher.alive("svc") == ["svc"]
    second.close()
    assert seen == [True, False]


def test_closed_watcher_hears_nothing() -> None:
    transport = InMemoryTransport()
    seen: list[bool] = []
    transport.watch_liveliness("svc/*", lambda k, a: seen.append(a)).close()
    transport.declare_token("svc/0")
    assert seen == []
