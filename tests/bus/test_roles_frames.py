"""Roles in a run with frames: every bus call of the env-worker (publishing frames), the factor-extractor
and the learner and evaluator waiting for slots, recorded on the in-process stack, is allowed by
``run_roles(..., frames=True)``, and the frames keys are nobody else's."""
from __future__ import annotations

import time

import pytest
import torch

from proto import topics
from services.bus.roles import FRAMES_ROLE, run_roles
from services.supervisor import inprocess
from services.supervisor.wiring import learning_services
from tests.bus.test_roles import RecordingTransport, allowed, denied
from tests.services.test_frames_inprocess import _cfg

RUN = "frames-mem"


def test_a_frames_run_uses_only_what_its_roles_allow(tmp_path) -> None:
    torch.set_num_threads(1)
    cfg = _cfg(tmp_path)
    RecordingTransport.calls.clear()
    patch = pytest.MonkeyPatch()
    patch.setattr(inprocess, "InMemoryTransport", RecordingTransport)
    try:
        stack = inprocess.InProcessStack(cfg, services=learning_services(inprocess.resolve(cfg)))
        stack.start()
        deadline = time.monotonic() + 240
        wanted = ("publish", topics.transitions(RUN, "w0"))  # the slots are frozen; the others started before
        while time.monotonic() < deadline and wanted not in RecordingTransport.calls[FRAMES_ROLE]:
            time.sleep(0.5)
        stack.stop(timeout=120)
    finally:
        patch.undo()
    roles = run_roles(RUN, "cdl", frames=True)
    calls = {role: made for role, made in RecordingTransport.calls.items() if role in roles}
    assert ("publish", topics.frames(RUN, "w0")) in calls["env-worker"]
    assert wanted in calls[FRAMES_ROLE] and ("serve", topics.env_spec(RUN)) in calls[FRAMES_ROLE]
    assert ("subscribe", topics.transitions(RUN)) in calls["dynamics-learner"]
    assert ("query", topics.env_spec(RUN)) in calls["graph-evaluator"]
    assert not denied(calls, roles)
    assert not allowed(roles["env-worker"], "publish", topics.transitions(RUN, "w0"))
    assert not allowed(roles["env-worker"], "serve", topics.env_spec(RUN))
    plain = run_roles(RUN, "cdl")
    assert FRAMES_ROLE not in plain and not allowed(plain["env-worker"], "publish", topics.frames(RUN, "w0"))
