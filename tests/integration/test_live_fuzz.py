"""Fuzzing a live run (issue 20, item 7): seeded random and mutated payloads on every topic the
services subscribe to, each published with the credentials of the role that owns the topic (what a
faulty or compromised process of that role could send). Every service keeps running (no restart),
counts what it refuses, and the run goes on (graph reports keep coming) and ends with its summary.
The counts are written to ``test-artifacts/fuzz/figures.json``."""
from __future__ import annotations

import json
import random
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from proto import topics
from proto.codec import encode
from proto.messages import SCHEMA_VERSION, Control, GraphReport, ScoredBatch, ServiceStats
from services.bus.credentials import read_credentials, role_file
from services.bus.router import free_tcp_port
from services.bus.zenoh_transport import ZenohTransport
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.runtime.config import build_config
from tests.integration.test_chaos import KINDS, Bus, command, start, stop, table
from tests import waiting

pytestmark = [pytest.mark.integration, pytest.mark.slow]
REPO = Path(__file__).resolve().parents[2]
SEED = 20
PER_TOPIC = 200
wait_for = waiting.wait_for
SUBSCRIBED = {"dynamics-learner": ("transitions", "graph", "control"),
              "graph-evaluator": ("transitions", "weights/cdl", "control"),
              "intrinsic-reward": ("transitions", "weights/cdl", "graph", "control"),
              "policy-learner": ("scored", "graph", "control"), "env-worker": ("weights/policy", "control"),
              "dashboard": ("graph", "stats", "control")}
"""Which of the fuzzed topics each service subscribes to (the roles table in docs/bus-roles.md)."""


def bases(run_id: str) -> dict[str, tuple[str, bytes]]:
    """Topic -> (the role that owns it, a valid payload to mutate): stale versions, a harmless command."""
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, graph="collider", num_objects=3, batch_steps=64, seed=99))
    batch = worker.collect()
    n = worker.spec.num_factors
    report = GraphReport(kind="cdl", weights_version=1, env_steps=0, updates=0, factor_names=worker.spec.factor_names,
                         cmi=np.zeros((n, n + 1), np.float32), adjacency=np.zeros((n, n + 1), np.uint8), threshold=0.02,
                         controllable=(), action_relevant=(), action_irrelevant=(), metrics={}, timestamp=0.0)
    scored = ScoredBatch(transitions=batch, intrinsic_reward=np.zeros(len(batch), np.float32), reward_kind="preddiff",
                         weights_version=0)
    stats = ServiceStats(service="env-worker", instance="fuzz", values={"env_steps": 1.0})
    # A local run has a bus user per process: env-worker 63 (of --max-workers 64) is one no process of the
    # run uses, so its keys are a fuzzer's own and no real worker's beats or batches are overwritten.
    return {topics.transitions(run_id, "w63"): ("env-worker-63", encode(batch)),
            topics.scored(run_id, "w63"): ("intrinsic-reward", encode(scored)),
            topics.weights(run_id, "cdl"): ("dynamics-learner", b""),
            topics.weights(run_id, "policy"): ("policy-learner", b""),
            topics.graph(run_id, "cdl"): ("graph-evaluator", encode(report)),
            topics.stats(run_id, "env-worker", "63"): ("env-worker-63", encode(stats)),
            topics.control(run_id, "all"): ("operator", encode(Control(command="checkpoint")))}


def payloads(rng: random.Random, base: bytes, count: int) -> list[bytes]:
    """Random bytes, bit-flipped and truncated copies of ``base``, and maps with a valid header and
    garbage fields, in turn."""
    out = []
    for i in range(count):
        kind = i % 4 if base else (0, 3)[i % 2]
        if kind == 0:
            out.append(rng.randbytes(rng.randint(0, 600)))
        elif kind == 1:
            mutated = bytearray(base)
            for _ in range(rng.randint(1, 8)):
                mutated[rng.randrange(len(mutated))] = rng.randrange(256)
            out.append(bytes(mutated))
        elif kind == 2:
            out.append(base[:rng.randrange(len(base))])
        else:
            garbage = {rng.choice(["state", "version", "tensors", "command", "cmi", "values", "x"]):
                       rng.choice([None, -1, 2**63 - 1, 1e308, "x" * rng.randint(0, 40), [1, [2]], {"a": b"\0"}])
                       for _ in range(rng.randint(0, 5))}
            name = rng.choice(["TransitionBatch", "ScoredBatch", "Weights", "GraphReport", "Control", "ServiceStats"])
            out.append(msgpack.packb({"type": name, "schema_version": SCHEMA_VERSION, **garbage}))
    return out


def rejected(bus: Bus, service: str) -> float:
    return bus.seen.latest(service, "messages_rejected")


def test_garbled_payloads_on_every_topic_are_counted_and_survived(tmp_path: Path) -> None:
    run_dir, port, dashboard = tmp_path / "run", free_tcp_port(), free_tcp_port()
    stack = start(command(run_dir, port, 0, dashboard))
    bus, sent, counts = None, {}, {}
    fuzzers: dict[str, ZenohTransport] = {}
    try:
        wait_for(lambda: set(KINDS) <= set(table(run_dir).get("processes", {})), 90, "every service started")
        connect = f"tcp/127.0.0.1:{port}"
        bus = Bus(connect, run_dir, "run")
        wait_for(lambda: bus.seen.reports and bus.seen.of("intrinsic-reward") and bus.seen.of("policy-learner"),
                 240, "a graph report and every service at work")
        before = {s: rejected(bus, s) for s in SUBSCRIBED}
        rng = random.Random(SEED)
        for key, (role, base) in bases("run").items():
            if role not in fuzzers:
                fuzzers[role] = ZenohTransport(connect, read_credentials(role_file(run_dir, role)))
            for payload in payloads(rng, base, PER_TOPIC):
                fuzzers[role].publish(key, payload)
                time.sleep(0.002)
            sent[key.split("/", 2)[2]] = PER_TOPIC
        fuzzed_at = time.time()
        wait_for(lambda: all(rejected(bus, s) - before[s] >= 0.95 * PER_TOPIC * len(t) for s, t in SUBSCRIBED.items()),
                 60, "every service refusing at least 95% of what it was sent (the rest decodes as valid)")
        wait_for(lambda: [r for at, r in bus.seen.reports if at > fuzzed_at + 2], 120, "a graph report after the fuzzing")
        counts = {s: int(rejected(bus, s) - before[s]) for s in before}
        assert all(counts[s] <= PER_TOPIC * len(t) for s, t in SUBSCRIBED.items()), counts
        restarts = {name: e["restarts"] for name, e in table(run_dir)["processes"].items()}
        assert not any(restarts.values()), restarts
    finally:
        for transport in fuzzers.values():
            transport.close()
        if bus is not None:
            bus.close()
        out = stop(stack, run_dir)
        artifacts = REPO / "test-artifacts" / "fuzz"
        artifacts.mkdir(parents=True, exist_ok=True)
        (artifacts / "figures.json").write_text(json.dumps({"seed": SEED, "sent": sent, "rejected": counts}, indent=1))
        print(json.dumps({"sent": sent, "rejected": counts}, indent=1))
    assert stack.returncode == 0, out
    assert json.loads((run_dir / "summary.json").read_text())["restarts"] == 0  # the supervisor survived it too
