"""Policy weights over a real Zenoh router: a worker started late acts with the current version at once.

The test plays the policy-learner (versions published through ``serve_latest``, exactly as the
service does), starts an env-worker process after several versions are out, and checks that the
worker's very first batches carry the current version, that a new version reaches it within 1 s,
and that it exports the version in use.
"""
from __future__ import annotations

import functools
import os
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest

from proto import topics
from proto.codec import decode, encode
from proto.messages import ServiceStats, TransitionBatch
from services.runtime.config import build_config
from services.bus.router import free_tcp_port, start_router, wait_for_router
from services.bus.zenoh_transport import ZenohTransport
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.policy_learner.config import PolicyLearnerConfig
from services.policy_learner.core import PolicyLearnerCore
from services.runtime.config import to_environ
from tests import waiting

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]
RUN = "late"


wait_for = functools.partial(waiting.wait_for, interval=0.01)

class Seen:
    """Batches (with their arrival times), worker stats and liveliness of the run."""

    def __init__(self, bus: ZenohTransport) -> None:
        self.lock = threading.Lock()
        self.batches: list[tuple[float, TransitionBatch]] = []
        self.stats: list[ServiceStats] = []
        self.alive_at: float | None = None
        bus.subscribe(topics.transitions(RUN), self._on_batch)
        bus.subscribe(topics.stats(RUN, "env-worker"), lambda k, p: self.stats.append(decode(p, ServiceStats)))
        bus.watch_liveliness(topics.alive(RUN, "env-worker"), self._on_alive)

    def _on_batch(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.batches.append((time.monotonic(), decode(payload, TransitionBatch)))

    def _on_alive(self, key: str, alive: bool) -> None:
        if alive and self.alive_at is None:
            self.alive_at = time.monotonic()

    def first_with(self, version: int) -> float | None:
        with self.lock:
            return next((t for t, b in self.batches if b.policy_version >= version), None)


def test_late_worker_catches_up_at_once_and_follows_new_versions(tmp_path: Path) -> None:
    port, metrics_port = free_tcp_port(), free_tcp_port()
    connect = f"tcp/127.0.0.1:{port}"
    router = start_router(connect)
    wait_for_router(connect)
    bus = ZenohTransport(connect)
    worker_cfg = build_config(EnvWorkerConfig, run_id=RUN, zenoh_connect=connect, run_dir=str(tmp_path), metrics_port=metrics_port,
                                 num_objects=3, batch_steps=64, max_steps_per_second=1000, follow_policy=True)
    learner = PolicyLearnerCore(PolicyLearnerConfig(hidden=16), EnvWorkerCore(worker_cfg).spec)
    latest = bus.serve_latest(topics.weights(RUN, "policy"))
    for _ in range(3):
        latest.set(encode(learner.weights()))
    seen = Seen(bus)
    env = {**os.environ, **to_environ(worker_cfg), "PYTHONUNBUFFERED": "1"}
    worker = subprocess.Popen([sys.executable, "-m", "services.env_worker"], cwd=REPO, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(lambda: seen.batches, 60, "the late worker's first batch")
        assert seen.alive_at is not None
        first = seen.batches[0][1]
        assert first.policy_version == 3, "the late worker's first batch must use the current policy"
        assert seen.batches[0][0] - seen.alive_at < 1.0
        assert all(b.policy_version == 3 for _, b in seen.batches)

        published = time.monotonic()
        latest.set(encode(learner.weights()))  # v4, pushed to the running worker
        switched = wait_for(lambda: seen.first_with(4), 5, "a batch acted with v4")
        assert switched - published < 1.0
        print(f"late worker: first batch {seen.batches[0][0] - seen.alive_at:.3f}s after going live, "
              f"v4 in use {switched - published:.3f}s after publication")
        wait_for(lambda: seen.stats and seen.stats[-1].values.get("policy_version") == 4, 5, "stats saying v4")
        body = urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=5).read().decode()
        assert "causeway_policy_version_in_use 4.0" in body
        assert "causeway_policy_weights_loaded_total 2.0" in body
    finally:
        worker.terminate()
        out, _ = worker.communicate(timeout=30)
        latest.close()
        bus.close()
        router.close()
    assert worker.returncode in (0, -15), out
