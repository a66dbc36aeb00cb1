"""``causeway status``: states, rates and the table from observations, and ``observe`` on the in-memory bus."""
from __future__ import annotations

import json
import threading
import time

import pytest

from proto import topics
from proto.codec import encode
from proto.messages import ServiceStats
from services.bus import InMemoryBus, InMemoryTransport, free_tcp_port
from services.cli import main as cli_main
from services.ops import status
from services.ops.observe import Observation, RunObserver, TokenChange, observe
from services.ops.target import Target

RUN = "r1"
T0 = 1_800_000_000.0


def beat(service: str, instance: str, at: float, **values: float) -> ServiceStats:
    return ServiceStats(service=service, instance=instance, values=values, timestamp=at)


def observation(alive: set[tuple[str, str]], changes: list[TokenChange] = (),
                beats: dict[tuple[str, str], list[ServiceStats]] | None = None) -> Observation:
    first = [TokenChange(i, True, T0) for i in sorted(alive | {c.instance for c in changes})]
    return Observation(T0, T0 + 2.5, frozenset(alive), tuple(first + list(changes)),
                       {i: tuple(b) for i, b in (beats or {}).items()})


def test_rate_is_taken_between_the_first_and_last_beat() -> None:
    beats = [beat("env-worker", "0", T0 + t, env_steps=s) for t, s in ((0.0, 1000), (1.0, 1500), (2.0, 2024))]
    assert status.rate(beats, status.RATES["env-worker"]) == pytest.approx(512.0)


def test_rate_restarts_after_a_counter_reset_and_needs_two_beats() -> None:
    spec = status.RATES["env-worker"]
    reset = [beat("env-worker", "0", T0 + t, env_steps=s) for t, s in ((0.0, 9000), (1.0, 256), (2.0, 768))]
    assert status.rate(reset, spec) == pytest.approx(512.0)
    assert status.rate(reset[:1], spec) is None
    assert status.rate([beat("env-worker", "0", T0, episodes=3)] * 2, spec) is None


def test_evaluator_reports_are_a_per_minute_rate() -> None:
    beats = [beat("graph-evaluator", "0", T0, reports=4), beat("graph-evaluator", "0", T0 + 10, reports=6)]
    assert status.rate(beats, status.RATES["graph-evaluator"]) == pytest.approx(12.0)


def test_states_alive_gone_restarted_and_no_stats_yet() -> None:
    worker, learner, evaluator, old = ("env-worker", "0"), ("dynamics-learner", "0"), ("graph-evaluator", "0"), ("env-worker", "1")
    obs = observation(
        alive={worker, learner, evaluator},
        changes=[TokenChange(worker, False, T0 + 1), TokenChange(worker, True, T0 + 2)],
        beats={learner: [beat(*learner, T0 + 0.5, updates=10), beat(*learner, T0 + 1.5, updates=40)],
               old: [beat(*old, T0 + 0.2, env_steps=256)]})
    rows = {(r.service, r.instance): r for r in status.statuses(obs)}

    assert rows[learner].state == "alive" and rows[learner].rate == pytest.approx(30.0)
    assert rows[learner].last_seen_s == pytest.approx(1.0)
    assert rows[worker].state == "restarted"
    assert rows[evaluator].state == "alive" and rows[evaluator].beats == 0
    assert rows[old].state == "gone" and not rows[old].token
    table = status.render_table(list(rows.values()))
    assert status.NO_STATS in next(line for line in table.splitlines() if line.startswith("graph-evaluator"))


def test_a_token_lost_during_the_window_is_gone() -> None:
    worker = ("env-worker", "0")
    obs = observation(alive=set(), changes=[TokenChange(worker, True, T0), TokenChange(worker, False, T0 + 1)])
    assert [r.state for r in status.statuses(obs)] == ["gone"]


def test_the_table_is_aligned_and_totals_sum_alive_rates() -> None:
    a, b = ("env-worker", "0"), ("env-worker", "12")
    obs = observation(alive={a, b}, beats={i: [beat(*i, T0, env_steps=0), beat(*i, T0 + 1, env_steps=500)] for i in (a, b)})
    rows = status.statuses(obs)
    lines = status.render_table(rows).splitlines()

    for column in ("STATE", "RATE", "VALUES"):
        at = lines[0].index(column)
        assert all(line[at - 2:at] == "  " and line[at] != " " for line in lines[1:])
    assert "500 steps/s" in lines[1] and "env_steps=500" in lines[1]
    assert status.totals(rows)["env-worker"] == {"alive": 2, "rate": 1000.0, "rate_unit": "steps/s"}
    assert "env-worker x2 1,000 steps/s" in status.render_totals(status.totals(rows))


def test_json_document() -> None:
    learner = ("dynamics-learner", "0")
    obs = observation(alive={learner}, beats={learner: [beat(*learner, T0 + 2, updates=5, messages_rejected=2)]})
    document = json.loads(json.dumps(status.report(Target("tcp/127.0.0.1:7447", RUN), obs)))

    assert document["run"] == RUN and document["router"] == "tcp/127.0.0.1:7447"
    (row,) = document["services"]
    assert row["service"] == "dynamics-learner" and row["state"] == "alive" and row["token"] is True
    assert row["values"] == {"updates": 5, "messages_rejected": 2} and row["rate"] is None
    assert document["totals"]["dynamics-learner"]["alive"] == 1


def test_observe_joins_tokens_and_beats_on_a_bus() -> None:
    bus = InMemoryBus()
    service, operator = InMemoryTransport(bus), InMemoryTransport(bus)
    token = service.declare_token(topics.alive(RUN, "env-worker", "0"))
    stop = threading.Event()

    def beats() -> None:
        steps = 0
        while not stop.wait(0.05):
            steps += 25
            service.publish(topics.stats(RUN, "env-worker", "0"),
                            encode(beat("env-worker", "0", time.time(), env_steps=steps)))

    thread = threading.Thread(target=beats)
    thread.start()
    try:
        obs = observe(operator, RUN, 0.4)
    finally:
        stop.set()
        thread.join()
    token.close()
    (row,) = status.statuses(obs)
    assert (row.service, row.instance, row.state) == ("env-worker", "0", "alive")
    assert row.beats >= 4 and row.rate == pytest.approx(500.0, rel=0.3)


def test_a_bad_stats_payload_is_counted_not_raised() -> None:
    bus = InMemoryBus()
    sender, operator = InMemoryTransport(bus), InMemoryTransport(bus)
    with RunObserver(operator, RUN) as observer:
        sender.publish(topics.stats(RUN, "env-worker", "0"), b"\x00not msgpack")
        assert observer.snapshot().rejected == 1


def test_unreachable_router_is_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    code = cli_main(["status", "--run", RUN, "--connect", f"tcp/127.0.0.1:{free_tcp_port()}"])
    assert code == 2
    assert "could not reach the Zenoh router" in capsys.readouterr().err


def test_render_says_when_nobody_is_there() -> None:
    text = status.render(Target("tcp/127.0.0.1:7447", RUN), observation(alive=set()))
    assert text == f"run {RUN} on tcp/127.0.0.1:7447: no live services (listened 2.5s)"


def test_render_has_the_table_and_the_totals() -> None:
    worker = ("env-worker", "0")
    obs = observation(alive={worker}, beats={worker: [beat(*worker, T0, env_steps=0), beat(*worker, T0 + 1, env_steps=50)]})
    lines = status.render(Target("tcp/127.0.0.1:7447", RUN), obs).splitlines()
    assert lines[0].split() == ["SERVICE", "INSTANCE", "STATE", "RATE", "LAST", "BEAT", "VALUES"]
    assert lines[1].split()[:5] == ["env-worker", "0", "alive", "50.0", "steps/s"]
    assert lines[-1] == "alive: env-worker x1 50.0 steps/s"
