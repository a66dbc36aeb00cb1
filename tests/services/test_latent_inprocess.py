"""A FLAM run with ``--label-latent-actions true``, in one process: the unchanged env-worker (frames beside
its transitions), dynamics-learner (FLAM) and factor-extractor (latent-action labels) over the in-memory
bus, wired by the supervisor's wiring. Every label the extractor publishes is the posterior of its step's
clip under the weights version it names, and every bus call is one its role allows."""
from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from causal.method import import_tensors
from causal.methods import model_from_config_json
from proto import topics
from proto.codec import decode
from proto.messages import FrameBatch, LatentActions, Weights
from services.bus.roles import FRAMES_ROLE, run_roles
from services.runtime.config import build_config
from services.supervisor import inprocess
from services.supervisor.config import RunConfig
from services.supervisor.wiring import learning_services, resolve, service_configs
from tests.bus.test_roles import RecordingTransport, allowed, denied
from tests.waiting import wait_for

RUN = "latent-mem"


def _cfg(tmp_path, **kw) -> RunConfig:
    settings = dict(env="multigrid-agents", method="flam", run_dir=str(tmp_path), run_id=RUN, progress=False,
                    label_latent_actions=True, worker_batch_steps=32, worker_max_steps_per_second=300,
                    flam_slot_dim=8, flam_action_dim=2, flam_iterations=1, flam_ae_updates=2, flam_batch_size=4,
                    flam_live_every=0, learner_warmup_steps=50, learner_publish_every_s=0.5)
    return build_config(RunConfig, **{**settings, **kw})


def test_wiring_labels_only_a_flam_run(tmp_path) -> None:
    cfg = resolve(_cfg(tmp_path))
    assert learning_services(cfg) == ("factor-extractor", "dynamics-learner")
    configs = service_configs(cfg, "memory")
    assert configs["env-worker"].frames_beside and not configs["env-worker"].publish_frames
    assert configs["factor-extractor"].mode == "latent-actions" and configs["factor-extractor"].method == "flam"
    plain = resolve(_cfg(tmp_path, label_latent_actions=False))
    assert learning_services(plain) == ("dynamics-learner",)
    assert service_configs(plain, "memory")["factor-extractor"].mode == "slots"
    with pytest.raises(ValueError, match="method 'dyno' has no latent actions"):
        resolve(_cfg(tmp_path, method="dyno", env="chemical-pixels"))
    with pytest.raises(ValueError, match="--worker-frame-stride must be 1"):
        resolve(_cfg(tmp_path, worker_frame_stride=2))


def test_a_flam_run_labels_the_workers_frames_in_process(tmp_path) -> None:
    torch.set_num_threads(1)
    cfg = _cfg(tmp_path)
    RecordingTransport.calls.clear()
    patch = pytest.MonkeyPatch()
    patch.setattr(inprocess, "InMemoryTransport", RecordingTransport)
    weights: dict[int, Weights] = {}
    frames: dict[tuple[str, int], FrameBatch] = {}
    labels: list[LatentActions] = []
    try:
        stack = inprocess.InProcessStack(cfg, services=learning_services(resolve(cfg)))
        bus = stack.transport()
        bus.subscribe(topics.weights(RUN, "flam"), lambda k, p: weights.setdefault(decode(p, Weights).version,
                                                                                  decode(p, Weights)))
        bus.subscribe(topics.frames(RUN), lambda k, p: frames.setdefault(
            (decode(p, FrameBatch).worker_id, decode(p, FrameBatch).seq), decode(p, FrameBatch)))
        bus.subscribe(topics.latent_actions(RUN), lambda k, p: labels.append(decode(p, LatentActions)))
        stack.start()
        try:
            wait_for(lambda: len(labels) >= 2, 240, "two batches of latent-action labels")
            time.sleep(1.0)
        finally:
            stack.stop(timeout=120)
    finally:
        patch.undo()
    for out in labels[:2]:
        source, used = frames[(out.worker_id, out.seq)], weights[out.weights_version]
        assert used.updates > 2, "labelled before the latent-action phase"
        model = model_from_config_json(used.config_json)
        import_tensors(model, used.tensors)
        model.eval()
        clips = torch.from_numpy(np.stack([source.frames[source.state_frame], source.frames[source.next_frame]], 1))
        with torch.no_grad():
            mean, log_sigma = model.lam.posterior(model.features(clips))
        np.testing.assert_allclose(out.mean, mean[:, 0].numpy(), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(out.log_sigma, log_sigma[:, 0].numpy(), rtol=1e-4, atol=1e-5)
        np.testing.assert_array_equal(out.step, source.step)
    roles = run_roles(RUN, "flam", latent=True)
    calls = {role: made for role, made in RecordingTransport.calls.items() if role in roles}
    assert ("publish", topics.frames(RUN, "w0")) in calls["env-worker"]
    assert ("publish", topics.transitions(RUN, "w0")) in calls["env-worker"]
    assert ("publish", topics.latent_actions(RUN, "w0")) in calls[FRAMES_ROLE]
    assert ("query", topics.weights(RUN, "flam")) in calls[FRAMES_ROLE]
    assert not denied(calls, roles)
    assert not allowed(roles[FRAMES_ROLE], "publish", topics.transitions(RUN, "w0"))
    assert not allowed(roles["env-worker"], "publish", topics.latent_actions(RUN, "w0"))
    with pytest.raises(ValueError, match="exclude each other"):
        run_roles(RUN, "flam", frames=True, latent=True)
