"""Roles in a SkiLD run: every bus call of the env-worker (skill batches, weights/skild-policy), the
graph-evaluator (induced graphs) and the policy-learner in SkiLD mode, recorded on the in-process stack,
is allowed by ``run_roles(..., "skild")``, and SkiLD's keys are nobody's in a run of another method."""
from __future__ import annotations

import time

import pytest
import torch

from proto import topics
from services.bus.roles import run_roles
from services.runtime.config import build_config
from services.supervisor import inprocess
from services.supervisor.config import RunConfig
from tests.bus.test_roles import RecordingTransport, allowed, denied

RUN = "skild-mem"


def test_a_skild_run_uses_only_what_its_roles_allow(tmp_path) -> None:
    torch.set_num_threads(1)
    cfg = build_config(RunConfig, method="skild", env="installing-printer", run_dir=str(tmp_path), run_id=RUN,
                       progress=False, worker_batch_steps=64, worker_max_steps_per_second=500,
                       learner_warmup_steps=64, learner_publish_every_s=0.5, evaluator_min_interval_s=0.5,
                       evaluator_min_heldout=32, policy_skill_learning_starts=64)
    RecordingTransport.calls.clear()
    patch = pytest.MonkeyPatch()
    patch.setattr(inprocess, "InMemoryTransport", RecordingTransport)
    try:
        stack = inprocess.InProcessStack(cfg)
        stack.start()
        deadline = time.monotonic() + 240
        wanted = ("publish", topics.induced(RUN, "skild", "w0"))
        while time.monotonic() < deadline and wanted not in RecordingTransport.calls["graph-evaluator"]:
            time.sleep(0.5)
        stack.stop(timeout=120)
    finally:
        patch.undo()
    roles = run_roles(RUN, "skild")
    calls = {role: made for role, made in RecordingTransport.calls.items() if role in roles}
    assert wanted in calls["graph-evaluator"]
    assert ("publish", topics.skills(RUN, "w0")) in calls["env-worker"]
    assert ("subscribe", topics.weights(RUN, "skild-policy")) in calls["env-worker"]
    assert {("subscribe", topics.skills(RUN)), ("subscribe", topics.induced(RUN, "skild")),
            ("serve", topics.weights(RUN, "skild-policy"))} <= calls["policy-learner"]
    assert not denied(calls, roles)
    plain = run_roles(RUN, "cdl")
    assert not allowed(plain["env-worker"], "publish", topics.skills(RUN, "w0"))
    assert not allowed(plain["graph-evaluator"], "publish", topics.induced(RUN, "cdl", "w0"))
    assert not allowed(plain["policy-learner"], "serve", topics.weights(RUN, "skild-policy"))
