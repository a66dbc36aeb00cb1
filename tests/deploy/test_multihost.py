"""The bus across hosts: a Zenoh router per host, routers meshed, on two network namespaces joined by
a veth link (tests/deploy/netns.py). Host A's router listens on the link; host B's router connects to
it. Every program is a client of its own host's router, as a service is of its host's.

- integration (CI): transitions from A reach a subscriber on B through the two routers, and the
  rate across the link is measured against the rate within B; a 10-second partition of the link
  is counted (batches lost, how long the stream stalled) and the stream goes on after it heals.
- integration, roles and TLS: a second pair of routers started from ``causeway bus-secrets`` output
  (users, the roles' access control; A listens on the link with ``tls/`` and a certificate the
  command made, B joins it over TLS as a user of its own): transitions published on A with the
  env-worker's credentials reach a subscriber with the learner's on B, at a rate measured against
  the open ``tcp/`` pair in the same run; a client without the CA, anonymous clients and a stop
  forged with the env-worker's credentials are refused, while the operator's stop crosses.
- slow: the same partition under the real services (an env-worker per host, the learner and the
  evaluator on B): the learner keeps updating through it and the run goes on. And the real services
  on the pair with roles and TLS: an env-worker on A with its role's credentials, the learner on B
  with its own; the learner trains on A's transitions across the TLS link.

Figures are written to ``test-artifacts/multihost/figures.json``.
"""
from __future__ import annotations

import json
import os
import select
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

import pytest

from services.cli import main as cli_main
from tests.deploy import REPO
from tests.deploy.netns import Host, TwoHosts, make_two_hosts

integration = pytest.mark.integration
PYTHON = str(REPO / ".venv" / "bin" / "python") if (REPO / ".venv" / "bin" / "python").exists() else sys.executable
ARTIFACTS = REPO / "test-artifacts" / "multihost"
PORT = 7447
RUN = "multihost"
LOCAL = f"tcp/127.0.0.1:{PORT}"
ROLES_PORT = 7448
"""The pair with roles and TLS: each host's clients on loopback, A's router on the link with tls/."""
LOCAL_ROLES = f"tcp/127.0.0.1:{ROLES_PORT}"


def _probe(*args: str) -> list[str]:
    return [PYTHON, "-m", "tests.deploy.bus_probe", *args]


@pytest.fixture
def hosts() -> Iterator[TwoHosts]:
    """Two hosts, a router on each, B's router meshed with A's across the link."""
    pair = make_two_hosts(f"{os.getpid() % 100000}")
    try:
        routers = [pair.a.start(_probe("router", "--listen", LOCAL, "--listen", f"tcp/{pair.a.address}:{PORT}"),
                                cwd=REPO),
                   pair.b.start(_probe("router", "--listen", LOCAL, "--connect", f"tcp/{pair.a.address}:{PORT}"),
                                cwd=REPO)]
        for router in routers:
            _wait_for_line(router, 60)
        yield pair
    finally:
        pair.close()


def _bus_secrets(out: Path, *args: str) -> Path:
    """``causeway bus-secrets`` for run ``RUN`` into ``out`` (the routers read their files there)."""
    assert cli_main(["bus-secrets", "--run", RUN, "--out", str(out), "--users-file", str(out / "secrets" / "router-users"),
                     "--router-config", str(REPO / "deploy" / "zenoh" / "router.json5"), *args]) == 0
    return out / "secrets"


@pytest.fixture
def secured(hosts: TwoHosts, tmp_path: Path) -> Iterator[tuple[TwoHosts, Path, Path]]:
    """Beside the open pair: a router per host from ``causeway bus-secrets`` (roles), A listening on the
    link with TLS (its certificate for its link address), B joining it as user ``router-b``."""
    link = f"tls/{hosts.a.address}:{ROLES_PORT}"
    a = _bus_secrets(tmp_path / "a", "--listen", link, "--listen", LOCAL_ROLES, "--tls-name", hosts.a.address,
                     "--mesh-user", "router-b")
    b = _bus_secrets(tmp_path / "b", "--listen", LOCAL_ROLES, "--join", link, "--join-credentials",
                     str(a / "router-b.credentials"), "--join-ca", str(a / "bus-ca.pem"))
    routers = [hosts.a.start(_probe("router", "--config", str(a / "router.json5"), "--listen", link,
                                    "--listen", LOCAL_ROLES), cwd=REPO),
               hosts.b.start(_probe("router", "--config", str(b / "router.json5"), "--listen", LOCAL_ROLES), cwd=REPO)]
    for router in routers:
        _wait_for_line(router, 60)
    yield hosts, a, b


def _wait_for_line(process: Any, timeout: float) -> str:
    """The first line a probe prints (a router prints one once it listens)."""
    ready, _, _ = select.select([process.stdout], [], [], timeout)
    assert ready, f"no output within {timeout} s"
    line = process.stdout.readline().decode()
    assert line, process.stderr.read().decode()[-3000:]
    return line


def _result(host: Host, process: Any, timeout: float) -> dict[str, Any]:
    out, err = process.communicate(timeout=timeout)
    assert process.returncode == 0, err.decode()[-3000:]
    return json.loads(out.decode().strip().splitlines()[-1])


def _steps_per_second(worker: dict[str, Any], steps_per_batch: int = 256) -> float:
    arrivals = worker["arrivals"]
    return (len(arrivals) - 1) * steps_per_batch / (arrivals[-1] - arrivals[0])


def _gaps(seqs: list[int]) -> list[tuple[int, int]]:
    """(last seq before, first seq after) of every hole in a stream of sequence numbers."""
    ordered = sorted(set(seqs))
    return [(x, y) for x, y in zip(ordered, ordered[1:]) if y != x + 1]


def _record(name: str, value: Any) -> None:
    """Add ``name`` to the figures file (kept across runs of single tests)."""
    path = ARTIFACTS / "figures.json"
    figures = json.loads(path.read_text()) if path.exists() else {}
    figures[name] = value
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(figures, indent=1) + "\n")


@integration
def test_meshed_routers_carry_transitions_across_the_link_and_within_a_host(hosts: TwoHosts) -> None:
    counter = hosts.b.start(_probe("count", "--connect", LOCAL, "--run", RUN, "--seconds", "18"), cwd=REPO)
    time.sleep(3)  # the counter subscribed, router B connected to router A
    across = hosts.a.start(_probe("publish", "--connect", LOCAL, "--run", RUN, "--worker", "a", "--seconds", "5"),
                           cwd=REPO)
    _result(hosts.a, across, 60)
    time.sleep(2)  # A's backlog drained: the two streams do not compete for the one subscriber
    within = hosts.b.start(_probe("publish", "--connect", LOCAL, "--run", RUN, "--worker", "b", "--seconds", "5"),
                           cwd=REPO)
    _result(hosts.b, within, 60)
    workers = _result(hosts.b, counter, 60)["workers"]
    assert set(workers) == {"a", "b"}, "batches from A must cross the link"
    rates = {name: round(_steps_per_second(w)) for name, w in workers.items()}
    lost = {name: w["lost"] for name, w in workers.items()}
    _record("unthrottled_transitions_per_second", {"across_the_link": rates["a"], "within_host_b": rates["b"],
                                                   "batches_received": {n: w["batches"] for n, w in workers.items()},
                                                   "batches_lost": lost,
                                                   "gaps": {n: _gaps(w["seqs"])[:5] for n, w in workers.items()}})
    # BLOCK loses nothing, across the link or not, as long as a publisher does not close its session
    # with batches still queued: without bus_probe's linger, ~5% of the last batches were lost.
    assert lost == {"a": 0, "b": 0}, (lost, {n: _gaps(w["seqs"])[:5] for n, w in workers.items()})
    assert rates["a"] > 1000 and rates["b"] > 1000, rates


@integration
def test_a_ten_second_partition_is_counted_and_the_stream_goes_on(hosts: TwoHosts) -> None:
    rate = 20.0  # batches/s: 5,120 env steps/s, about what two throttled env-workers publish
    counter = hosts.b.start(_probe("count", "--connect", LOCAL, "--run", RUN, "--seconds", "42"), cwd=REPO)
    time.sleep(3)
    publisher = hosts.a.start(_probe("publish", "--connect", LOCAL, "--run", RUN, "--worker", "a",
                                     "--rate", str(rate), "--seconds", "36"), cwd=REPO)
    time.sleep(8)
    partitioned_at = time.time()
    hosts.partition()
    time.sleep(10)
    hosts.heal()
    healed_at = time.time()
    sent = _result(hosts.a, publisher, 90)
    counted = _result(hosts.b, counter, 90)
    worker = counted["workers"]["a"]
    arrivals = [counted["started"] + t for t in worker["arrivals"]]
    after_heal = [t for t in arrivals if t > healed_at]
    gaps = [later - earlier for earlier, later in zip(arrivals, arrivals[1:])]
    figures = {"batches_sent": sent["sent"], "batches_received": worker["batches"], "lost_in_stream": worker["lost"],
               "never_received": sent["sent"] - worker["batches"], "longest_stall_s": round(max(gaps), 2),
               "first_batch_after_heal_s": round(after_heal[0] - healed_at, 2) if after_heal else None,
               "received_after_heal": len(after_heal), "publish_rate_batches_per_s": rate,
               "partition_s": round(healed_at - partitioned_at, 2)}
    _record("ten_second_partition_raw_bus", figures)
    assert worker["duplicates"] == 0, figures
    assert len(after_heal) >= 0.5 * rate * 5, f"the stream did not resume after the heal: {figures}"
    assert worker["last_seq"] >= sent["sent"] - 2 * rate, figures
    assert figures["longest_stall_s"] >= 5, "a 10-second partition must show as a stall"


@integration
def test_with_roles_transitions_cross_a_tls_link_between_routers(secured: tuple[TwoHosts, Path, Path]) -> None:
    hosts, a, b = secured
    learner = ("--credentials", str(b / "dynamics-learner.credentials"))
    worker = ("--credentials", str(a / "env-worker.credentials"))
    counters = {"tls_with_roles": hosts.b.start(_probe("count", "--connect", LOCAL_ROLES, "--run", RUN, "--seconds", "24",
                                                       *learner), cwd=REPO),
                "tcp_open": hosts.b.start(_probe("count", "--connect", LOCAL, "--run", RUN, "--seconds", "24"), cwd=REPO)}
    time.sleep(3)  # the counters subscribed, router B joined router A
    publishers = {"tls_with_roles": (LOCAL_ROLES, *worker), "tcp_open": (LOCAL,)}
    for name, (connect, *bus) in publishers.items():
        _result(hosts.a, hosts.a.start(_probe("publish", "--connect", connect, "--run", RUN, "--worker", "a",
                                              "--seconds", "5", *bus), cwd=REPO), 60)
        time.sleep(2)  # drained before the next stream
    workers = {name: _result(hosts.b, counter, 60)["workers"] for name, counter in counters.items()}
    assert set(workers["tls_with_roles"]) == {"a"}, "env-worker batches from A must reach the learner's subscriber on B"
    rates = {name: round(_steps_per_second(w["a"])) for name, w in workers.items()}
    lost = {name: w["a"]["lost"] for name, w in workers.items()}
    _record("tls_link_vs_tcp_link_transitions_per_second",
            {**rates, "ratio_tls_with_roles_to_tcp_open": round(rates["tls_with_roles"] / rates["tcp_open"], 3),
             "batches_received": {n: w["a"]["batches"] for n, w in workers.items()}, "batches_lost": lost})
    assert lost == {"tls_with_roles": 0, "tcp_open": 0}, lost
    assert min(rates.values()) > 1000, rates


@integration
def test_with_roles_the_tls_routers_refuse_strangers_and_wrong_roles(secured: tuple[TwoHosts, Path, Path]) -> None:
    hosts, a, b = secured
    link = f"tls/{hosts.a.address}:{ROLES_PORT}"
    ca, worker = str(a / "bus-ca.pem"), str(a / "env-worker.credentials")
    attempts = {"tls_without_ca": ("--connect", link, "--credentials", worker),
                "tls_anonymous": ("--connect", link, "--root-ca", ca),
                "local_anonymous_on_b": ("--connect", LOCAL_ROLES),
                "other_hosts_password_on_b": ("--connect", LOCAL_ROLES, "--credentials", worker),
                "tls_with_ca_and_credentials": ("--connect", link, "--credentials", worker, "--root-ca", ca)}
    started = {name: hosts.b.start(_probe("open", *args), cwd=REPO) for name, args in attempts.items()}
    opened = {name: _result(hosts.b, process, 60)["opened"] for name, process in started.items()}
    assert opened == {"tls_without_ca": False, "tls_anonymous": False, "local_anonymous_on_b": False,
                      "other_hosts_password_on_b": False, "tls_with_ca_and_credentials": True}, opened
    stop = f"causeway/{RUN}/control/all"
    watcher = hosts.b.start(_probe("watch", "--connect", LOCAL_ROLES, "--key", stop, "--seconds", "12",
                                   "--credentials", str(b / "supervisor.credentials")), cwd=REPO)
    _wait_for_line(watcher, 60)
    time.sleep(1)
    puts = [hosts.a.start(_probe("put", "--connect", LOCAL_ROLES, "--key", stop, "--payload", f"stop-by-{role}",
                                 "--seconds", "3", "--credentials", str(a / f"{role}.credentials")), cwd=REPO)
            for role in ("env-worker", "operator")]
    sent = [_result(hosts.a, put, 60)["sent"] for put in puts]
    assert min(sent) > 0, sent
    payloads = _result(hosts.b, watcher, 60)["payloads"]
    _record("tls_link_refusals", {"opened": opened, "stops_received_on_b": payloads,
                                  "stops_sent_from_a": {"stop-by-env-worker": sent[0], "stop-by-operator": sent[1]}})
    assert set(payloads) == {"stop-by-operator"}, payloads  # the env-worker's stop never crossed


def _service_env(host: Host, run_dir: Path, **settings: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAUSEWAY_")}
    env.update({"CAUSEWAY_RUN_ID": RUN, "CAUSEWAY_ZENOH_CONNECT": LOCAL, "CAUSEWAY_RUN_DIR": str(run_dir),
                "CAUSEWAY_METRICS_PORT": "0", "CAUSEWAY_ENV": "chemical", "CAUSEWAY_GRAPH": "full",
                "CAUSEWAY_NUM_OBJECTS": "10", **settings})
    return env


def _status(host: Host, connect: str = LOCAL, *bus: str) -> dict[str, Any]:
    result = host.run([str(REPO / ".venv" / "bin" / "causeway"), "status", "--run", RUN, "--connect", connect,
                       "--listen-s", "4", "--json", *bus], timeout=60, cwd=REPO)
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout)


def _value(status: dict[str, Any], service: str, key: str) -> float:
    return sum(r["values"].get(key, 0.0) for r in status["services"] if r["service"] == service and r["token"])


@pytest.mark.slow
def test_services_on_two_hosts_ride_out_a_partition(hosts: TwoHosts) -> None:
    logs = ARTIFACTS / "services"
    logs.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="causeway-multihost-") as tmp:
        run_dir = Path(tmp)
        for host, index in ((hosts.a, "1"), (hosts.b, "2")):
            host.start([PYTHON, "-m", "services.env_worker"], cwd=REPO, log=logs / f"env-worker-{index}.log",
                       env=_service_env(host, run_dir / host.namespace, CAUSEWAY_WORKER_INDEX=index,
                                        CAUSEWAY_INSTANCE=index))
        for service in ("dynamics_learner", "graph_evaluator"):
            hosts.b.start([PYTHON, "-m", f"services.{service}"], cwd=REPO, log=logs / f"{service}.log",
                          env=_service_env(hosts.b, run_dir / hosts.b.namespace))
        counter = hosts.b.start(_probe("count", "--connect", LOCAL, "--run", RUN, "--seconds", "120"), cwd=REPO)
        time.sleep(45)
        before = _status(hosts.b)
        assert _value(before, "env-worker", "env_steps") > 0 and _value(before, "dynamics-learner", "updates") > 0
        partitioned_at = time.time()
        hosts.partition()
        time.sleep(3)
        during = _status(hosts.b)
        time.sleep(max(0.0, 10 - (time.time() - partitioned_at)))
        hosts.heal()
        healed_at = time.time()
        time.sleep(20)
        after = _status(hosts.b)
        counted = _result(hosts.b, counter, 120)
    workers = counted["workers"]
    across, within = workers["w1"], workers["w2"]
    arrivals = [counted["started"] + t for t in across["arrivals"]]
    before_partition = {name: {**w, "arrivals": [t for t in w["arrivals"] if counted["started"] + t < partitioned_at]}
                        for name, w in workers.items()}
    figures = {
        "transitions_per_second_before_the_partition": {
            "across_the_link_w1": round(_steps_per_second(before_partition["w1"])),
            "within_host_w2": round(_steps_per_second(before_partition["w2"]))},
        "lost_batches_w1": across["lost"], "lost_batches_w2": within["lost"],
        "w1_batches_after_heal": len([t for t in arrivals if t > healed_at]),
        "longest_stall_w1_s": round(max(b - a for a, b in zip(arrivals, arrivals[1:])), 2),
        "env_workers_seen_on_b": {"before": len([r for r in before["services"] if r["service"] == "env-worker"
                                                 and r["token"]]),
                                  "during": len([r for r in during["services"] if r["service"] == "env-worker"
                                                 and r["token"]])},
        "env_workers_seen_on_b_after_heal": len([r for r in after["services"] if r["service"] == "env-worker"
                                                 and r["token"]]),
        "learner_updates": {"before": _value(before, "dynamics-learner", "updates"),
                            "after_heal": _value(after, "dynamics-learner", "updates")},
        "learner_env_steps": {"before": _value(before, "dynamics-learner", "env_steps"),
                              "after_heal": _value(after, "dynamics-learner", "env_steps")},
    }
    _record("ten_second_partition_services", figures)
    assert figures["w1_batches_after_heal"] > 0, figures
    assert figures["env_workers_seen_on_b"]["before"] == 2 and figures["env_workers_seen_on_b_after_heal"] == 2, figures
    assert figures["learner_updates"]["after_heal"] > figures["learner_updates"]["before"], figures
    assert _value(after, "env-worker", "env_steps") > _value(before, "env-worker", "env_steps"), figures


@pytest.mark.slow
def test_services_with_roles_train_across_a_tls_link(secured: tuple[TwoHosts, Path, Path]) -> None:
    hosts, a, b = secured
    logs = ARTIFACTS / "services-tls"
    logs.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="causeway-multihost-tls-") as tmp:
        run_dir = Path(tmp)
        hosts.a.start([PYTHON, "-m", "services.env_worker"], cwd=REPO, log=logs / "env-worker-1.log",
                      env=_service_env(hosts.a, run_dir / "a", CAUSEWAY_ZENOH_CONNECT=LOCAL_ROLES,
                                       CAUSEWAY_BUS_CREDENTIALS=str(a / "env-worker.credentials"),
                                       CAUSEWAY_WORKER_INDEX="1", CAUSEWAY_INSTANCE="1"))
        hosts.b.start([PYTHON, "-m", "services.dynamics_learner"], cwd=REPO, log=logs / "dynamics_learner.log",
                      env=_service_env(hosts.b, run_dir / "b", CAUSEWAY_ZENOH_CONNECT=LOCAL_ROLES,
                                       CAUSEWAY_BUS_CREDENTIALS=str(b / "dynamics-learner.credentials")))
        operator = ("--bus-credentials", str(b / "operator.credentials"))
        deadline, status = time.monotonic() + 150, {"services": []}
        while time.monotonic() < deadline:
            time.sleep(10)
            status = _status(hosts.b, LOCAL_ROLES, *operator)
            if _value(status, "dynamics-learner", "updates") > 0:
                break
        first = status
        time.sleep(15)
        later = _status(hosts.b, LOCAL_ROLES, *operator)
    figures = {"env_workers_seen_on_b": len([r for r in later["services"] if r["service"] == "env-worker" and r["token"]]),
               "learner_env_steps": [_value(first, "dynamics-learner", "env_steps"),
                                     _value(later, "dynamics-learner", "env_steps")],
               "learner_updates": [_value(first, "dynamics-learner", "updates"),
                                   _value(later, "dynamics-learner", "updates")]}
    _record("services_with_roles_across_a_tls_link", figures)
    assert figures["env_workers_seen_on_b"] == 1, figures  # A's worker, through the TLS link, with its role
    assert 0 < figures["learner_env_steps"][0] < figures["learner_env_steps"][1], figures
    assert figures["learner_updates"][1] > figures["learner_updates"][0] > 0, figures
