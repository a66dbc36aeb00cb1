"""The dynamics-learner with ``--method flam``: a real learner core on MultiGrid-agents transitions from
a real env-worker core trains FLAM's phases, exports the live scores as the ``causeway_dynamics_live_score``
gauge, and publishes weights that rebuild the same model after the msgpack round trip."""
from __future__ import annotations

from types import SimpleNamespace

import torch

from causal.method import import_tensors
from causal.methods import model_from_config_json
from proto.codec import decode, encode
from proto.messages import Weights
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.dynamics_learner.service import _Metrics, _train
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.runtime.config import build_config
from services.runtime.metrics import ServiceMetrics

torch.set_num_threads(1)
FLAM = dict(method="flam", flam_slot_dim=8, flam_action_dim=2, flam_iterations=1, flam_ae_updates=2,
            flam_batch_size=4, flam_live_every=2, flam_live_videos=2, flam_horizon=3, warmup_steps=50)


def test_the_learner_trains_flam_exports_live_scores_and_publishes_weights() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="multigrid-agents", batch_steps=64))
    core = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **FLAM), worker.spec)
    core.ingest(worker.collect())
    service_metrics = ServiceMetrics("dynamics-learner", "0")
    metrics = _Metrics(SimpleNamespace(metrics=service_metrics))
    for _ in range(4):
        _train(core, metrics)
    assert core.trainer.updates == 4 and core.last_stats["phase"] == 1.0
    live = {s.labels["name"]: s.value for family in service_metrics.registry.collect()
            if family.name == "causeway_dynamics_live_score" for s in family.samples}
    assert set(live) == {"psnr", "dci_d", "dci_c", "dci_i", *(f"slot{k}_kl" for k in range(5))}
    assert all(live[name] == core.last_stats[f"live_{name}"] for name in live) and live["psnr"] > 0
    weights = decode(encode(core.weights()), Weights)
    assert weights.model == "flam" and weights.updates == 4
    model = model_from_config_json(weights.config_json)
    import_tensors(model, weights.tensors)
    for name, value in model.state_dict().items():
        assert torch.equal(value, core.trainer.model.state_dict()[name]), name


def test_with_longer_clips_the_learner_trains_flam_on_consecutive_states_of_its_replay() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="multigrid-agents", batch_steps=64))
    core = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **FLAM, flam_clip_frames=4), worker.spec)
    core.ingest(worker.collect())
    given: list[torch.Tensor] = []
    update_clips = core.trainer.update_clips
    core.trainer.update_clips = lambda states: given.append(states) or update_clips(states)
    for _ in range(4):
        core.train_step()
    assert core.trainer.updates == 4 and core.last_stats["phase"] == 1.0
    assert all(torch.isfinite(torch.tensor(v)) for v in core.last_stats.values())
    clips = torch.stack(given)
    assert clips.shape == (4, 4, 4, 8)  # updates, batch, frames, 4 agents' (x, y)
    steps = (clips[:, :, 1:] - clips[:, :, :-1]).abs()  # each agent moves at most one cell per step
    assert steps.max() <= 1 and bool((steps.sum(-1) > 0).any())
