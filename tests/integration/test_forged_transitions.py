"""Transitions the env cannot produce, forged on the bus (issue 20, item 3): a real dynamics-learner
process behind a real Zenoh router refuses batches whose factor values lie outside the env's declared
observation space (the issue's finite 3e38 positions) or that hold no category index where the spec
declares a categorical factor; it counts them and never stores them, while real batches around them
are taken."""
from __future__ import annotations

import dataclasses
import functools
import os
import re
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from proto import topics
from proto.codec import decode, encode
from proto.messages import ServiceStats, TransitionBatch
from services.bus.router import free_tcp_port, start_router, wait_for_router
from services.bus.zenoh_transport import ZenohTransport
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.runtime.config import build_config, to_environ
from tests import waiting

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]
RUN = "forged"
wait_for = functools.partial(waiting.wait_for, interval=0.1)


def forge(batch: TransitionBatch, column: int, value: float) -> TransitionBatch:
    state = batch.state.copy()
    state[:, column] = value
    return dataclasses.replace(batch, state=state)


def metric(port: int, name: str) -> float | None:
    body = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    found = re.search(rf"^{re.escape(name)} ([0-9.e+]+)$", body, re.M)
    return float(found.group(1)) if found else None


def test_the_learner_refuses_transitions_outside_the_envs_space_and_keeps_the_real_ones(tmp_path: Path) -> None:
    port, metrics_port = free_tcp_port(), free_tcp_port()
    connect = f"tcp/127.0.0.1:{port}"
    router = start_router(connect)
    wait_for_router(connect)
    bus = ZenohTransport(connect)
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=64, seed=11))
    assert worker.spec.state_low is not None  # Chemical declares its observation space
    spec = bus.serve_latest(topics.env_spec(RUN))
    spec.set(encode(worker.spec))
    beats: list[ServiceStats] = []
    bus.subscribe(topics.stats(RUN, "dynamics-learner"), lambda k, p: beats.append(decode(p, ServiceStats)))
    cfg = build_config(DynamicsLearnerConfig, run_id=RUN, zenoh_connect=connect, run_dir=str(tmp_path),
                       metrics_port=metrics_port, metrics_host="127.0.0.1", warmup_steps=100_000)
    env = {**os.environ, **to_environ(cfg), "PYTHONUNBUFFERED": "1"}
    learner = subprocess.Popen([sys.executable, "-m", "services.dynamics_learner"], cwd=REPO, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(lambda: beats, 120, "the learner's first beat (it has the EnvSpec)")
        good = [worker.collect() for _ in range(2)]
        position = worker.spec.factor_names.index("obj0.x")  # a continuous factor: declared in [-1e6, 1e6]
        forged = [forge(good[0], position, 3e38), forge(good[0], 0, 2.5)]  # column 0: obj0.color, categorical
        for batch in (good[0], *forged, good[1]):
            bus.publish(topics.transitions(RUN, worker.worker_id), encode(batch))
        rejected = 'causeway_messages_rejected_total{reason="inconsistent"}'
        wait_for(lambda: metric(metrics_port, rejected) == 2.0 and metric(metrics_port, "causeway_learner_env_steps") == 128.0,
                 60, "two batches refused and two taken")
        assert beats[-1].values["messages_rejected"] <= 2.0
    finally:
        learner.terminate()
        out, _ = learner.communicate(timeout=60)
        spec.close()
        bus.close()
        router.close()
    assert learner.returncode in (0, -15), out
    assert "outside the env's observation space (column 1: 3e+38 not in [-1e+06, 1e+06])" in out
    assert "2.5 is no category index of" in out
