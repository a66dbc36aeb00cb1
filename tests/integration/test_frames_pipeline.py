"""Frames end to end on loopback (issue 24, item 5): a real Zenoh router with the run's roles, a real
env-worker process publishing chemical-pixels frames, a real factor-extractor process learning slots from
them and publishing slot transitions, received by a subscriber with the dynamics-learner's credentials,
which also gets the slot spec from ``env/spec`` as the learner does. The extractor, stopped and started
again, resumes its frozen slots from its checkpoint and publishes at once, in the same factor space."""
from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from proto import topics
from proto.codec import decode
from proto.fits import check_fits
from proto.messages import EnvSpec, TransitionBatch
from services.bus.credentials import read_credentials, role_file, write_run_secrets
from services.bus.roles import access_control, new_passwords, run_roles
from services.bus.router import free_tcp_port, start_router, wait_for_router
from services.bus.zenoh_transport import ZenohTransport
from services.env_worker.config import EnvWorkerConfig
from services.factor_extractor.config import FactorExtractorConfig
from services.runtime.config import build_config, to_environ
from tests import waiting

pytestmark = [pytest.mark.integration, pytest.mark.slow]  # two process starts each way: ~140 s at load 14; the fast in-process twin is tests/services/test_frames_inprocess.py
REPO = Path(__file__).resolve().parents[2]
RUN = "frames"
wait_for = functools.partial(waiting.wait_for, interval=0.1)


def start(module: str, cfg, role: str) -> subprocess.Popen:
    env = {**os.environ, **to_environ(cfg), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", module], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def stop(process: subprocess.Popen) -> str:
    process.terminate()
    out, _ = process.communicate(timeout=60)
    assert process.returncode in (0, -15), out
    return out


def test_worker_frames_become_slot_transitions_for_the_learner(tmp_path: Path) -> None:
    roles = run_roles(RUN, "cdl", frames=True)
    auth = write_run_secrets(tmp_path, new_passwords(tuple(roles)), access_control(roles))
    connect = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = start_router(connect, auth)
    wait_for_router(connect, credentials=read_credentials(role_file(tmp_path, "operator")))
    common = {"run_id": RUN, "zenoh_connect": connect, "run_dir": str(tmp_path), "checkpoint_every_s": 600.0}
    worker_cfg = build_config(EnvWorkerConfig, env="chemical-pixels", num_objects=3, graph="chain", batch_steps=64,
                              publish_frames=True, max_steps_per_second=400, **common,
                              bus_credentials=str(role_file(tmp_path, "env-worker")))
    extractor_cfg = build_config(FactorExtractorConfig, ae_updates=4, slot_updates=4, warmup_frames=64,
                                 slot_batch_size=8, **common, bus_credentials=str(role_file(tmp_path, "factor-extractor")))
    learner = ZenohTransport(connect, read_credentials(role_file(tmp_path, "dynamics-learner")))
    batches: list[TransitionBatch] = []
    learner.subscribe(topics.transitions(RUN), lambda k, p: batches.append(decode(p, TransitionBatch)))
    worker = start("services.env_worker", worker_cfg, "env-worker")
    extractor = start("services.factor_extractor", extractor_cfg, "factor-extractor")
    try:
        spec = wait_for(lambda: [decode(p, EnvSpec) for _, p in learner.query(topics.env_spec(RUN), timeout=1.0)],
                        120, "the slot spec on env/spec")[0]
        assert spec.env_id == "chemical-pixels-slots" and spec.factor_names == ("background", "obj0", "obj1", "obj2")
        wait_for(lambda: len(batches) >= 2, 60, "two slot transition batches")
        for batch in batches[:2]:
            check_fits(spec, batch)
            assert batch.state.shape == (64, 4 * 16) and batch.worker_id == "w0"
        assert batches[1].seq > batches[0].seq
        out = stop(extractor)
        assert "slots frozen after 8 updates: publishing slot transitions in object order" in out, out
        seen = len(batches)
        extractor = start("services.factor_extractor", extractor_cfg, "factor-extractor")
        wait_for(lambda: len(batches) > seen, 60, "slot transitions from the restarted extractor")
        out = stop(extractor)
        assert "factor-extractor resumed from" in out and "slots frozen after 8 updates" in out, out
        again = [decode(p, EnvSpec) for _, p in learner.query(topics.env_spec(RUN), timeout=1.0)]
        assert not again  # the extractor serves the spec; stopped, nobody does
        assert np.isfinite(batches[-1].state).all() and batches[-1].state.shape[1] == spec.state_dim
    finally:
        for process in (extractor, worker):
            if process.poll() is None:
                process.kill()
                process.communicate(timeout=60)
        learner.close()
        router.close()
    assert worker.returncode is not None
