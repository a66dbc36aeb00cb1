"""FLAM as a method (chapter 8): the trainer's phases in order (FSQ autoencoder, then the latent action
model), the live scores, weights through the msgpack ``Weights`` message, checkpoint round trips, the
settings it refuses, and the ``latent_actions`` scorer of a run's summary."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from causal.factored import FactorLayout
from causal.flam_learner import (FLAMRunConfig, FLAMTrainer, LatentActionScores, check_layout, multigrid_geometry,
                                 token_labels)
from causal.method import export_tensors, import_tensors
from causal.methods import get_method, model_from_config_json
from envs.chemical_pixels import ChemicalPixelsEnv
from envs.multigrid_agents import MultiGridAgentsEnv, record_videos
from proto.codec import decode, encode
from proto.messages import Weights

torch.set_num_threads(1)
TINY = FLAMRunConfig(slot_dim=8, action_dim=2, iterations=1, ae_updates=2, lam_updates=4, batch_size=4,
                     live_every=2, live_videos=2, horizon=3)


def _env() -> MultiGridAgentsEnv:
    return MultiGridAgentsEnv(num_agents=2, grid_size=4)


def _layout() -> FactorLayout:
    return FactorLayout.from_spec(_env().env_spec())


def _batch(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    videos = record_videos(_env(), 2, 2, seed=seed)
    positions = torch.from_numpy(videos["positions"].reshape(2, 3, 4).astype(np.float32))
    return positions[:, :-1].reshape(4, 4), torch.zeros(4, 1), positions[:, 1:].reshape(4, 4)


def _params(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def _changed(before: list[torch.Tensor], module: torch.nn.Module) -> bool:
    return any(not torch.equal(a, b) for a, b in zip(before, module.parameters()))


def test_phases_train_in_order_and_the_autoencoder_is_frozen_after_its_own() -> None:
    trainer = FLAMTrainer(_layout(), TINY, seed=0)
    model = trainer.model
    for u in range(5):
        ae, lam = _params(model.autoencoder), _params(model.lam)
        stats = trainer.update(*_batch(u))
        assert stats["phase"] == float(u >= 2)
        assert _changed(ae, model.autoencoder) == (u < 2) and _changed(lam, model.lam) == (u >= 2)
        assert all(math.isfinite(v) for v in stats.values())
    assert not any(p.requires_grad for p in model.autoencoder.parameters())


def test_live_scores_come_every_live_every_latent_action_updates() -> None:
    trainer = FLAMTrainer(_layout(), TINY, seed=0)
    live = [sorted(k for k in trainer.update(*_batch(u)) if k.startswith("live_")) for u in range(6)]
    expected = ["live_dci_c", "live_dci_d", "live_dci_i", "live_psnr", "live_slot0_kl", "live_slot1_kl", "live_slot2_kl"]
    assert live == [[], [], expected, [], expected, []]  # latent-action updates 1 and 3 of 4


def test_the_binding_weight_reaches_the_latent_action_model_and_its_loss() -> None:
    trainer = FLAMTrainer(_layout(), FLAMRunConfig(**{**TINY.__dict__, "mask_binding": 2.0}), seed=0)
    assert trainer.model.lam.config.mask_binding == 2.0
    stats = [trainer.update(*_batch(u)) for u in range(3)]  # the third is a latent-action update, masks kept
    assert stats[2]["phase"] == 1.0 and math.isfinite(stats[2]["loss"]) and "mask_binding_ce" in stats[2]


@pytest.mark.parametrize("ablation", [{}, {"temporal_attention": False, "coupling": "global"}])
def test_weights_travel_as_a_msgpack_message_and_rebuild_the_same_model(ablation: dict) -> None:
    """Also for Table 8.5's ablations: the config carries them, so the receiver builds the same networks."""
    trainer = FLAMTrainer(_layout(), FLAMRunConfig(**{**TINY.__dict__, **ablation}), seed=0)
    for u in range(3):
        trainer.update(*_batch(u))
    sent = Weights(model="flam", version=1, config_json=trainer.config_json(), tensors=export_tensors(trainer.model),
                   updates=trainer.updates, env_steps=12)
    received = decode(encode(sent), Weights)
    model = model_from_config_json(received.config_json)
    import_tensors(model, received.tensors)
    videos = record_videos(_env(), 2, 3, seed=7)
    frames = torch.from_numpy(videos["frames"])
    trainer.model.eval(), model.eval()
    with torch.no_grad():
        expected = trainer.model.lam.infer(trainer.model.features(frames))
        assert torch.equal(model.lam.infer(model.features(frames)), expected)
    assert (model.lam.factorizer.temporal is None) == (ablation.get("temporal_attention") is False)
    assert model.lam.fdm.coupled == (ablation.get("coupling") == "global")


def test_a_checkpoint_resumes_the_same_training() -> None:
    first = FLAMTrainer(_layout(), TINY, seed=0)
    for u in range(3):
        first.update(*_batch(u))
    second = FLAMTrainer(_layout(), TINY, seed=1)
    second.load_state_dict(first.state_dict())
    assert second.phase == "latent_actions" and not any(p.requires_grad for p in second.model.autoencoder.parameters())
    torch.manual_seed(5)
    a = first.update(*_batch(3))
    torch.manual_seed(5)
    b = second.update(*_batch(3))
    assert a["loss"] == pytest.approx(b["loss"], rel=1e-6)
    for p, q in zip(first.model.parameters(), second.model.parameters()):
        assert torch.allclose(p, q, atol=1e-6)


def test_the_scorer_writes_the_contract_keys_of_unseen_videos() -> None:
    trainer = FLAMTrainer(_layout(), TINY, seed=0)
    for u in range(3):
        trainer.update(*_batch(u))
    scores = LatentActionScores(videos=12).scores(trainer.model, _env().env_spec())
    dci_keys = [f"dci_{x}{suffix}" for suffix in ("", "_positions", "_ceiling") for x in "dci"]
    assert {"psnr", *dci_keys} <= set(scores)
    assert 0.0 < scores["psnr"] < 100.0 and all(0.0 <= scores[k] <= 1.0 for k in dci_keys)
    assert len(scores["slot_kl"]) == 3 and scores["videos"] == 12 and scores["horizon"] == 3
    json.dumps(scores)


def test_the_latent_action_learning_rate_decays_over_its_own_updates_and_may_change_on_resume() -> None:
    decayed = dataclasses.replace(TINY, lr=2e-3, lr_final=1e-4, lr_decay_updates=2)
    trainer = FLAMTrainer(_layout(), decayed, seed=0)
    rates = []
    for u in range(5):
        rates.append(trainer.lr)
        trainer.update(*_batch(u))
        if trainer.phase == "latent_actions":  # the rate the optimiser used for the update just made
            assert trainer.lam_trainer.optimizer.param_groups[0]["lr"] == pytest.approx(rates[-1], rel=1e-9)
    # two autoencoder updates at ae_lr, then the cosine over the latent-action updates: lr, midway, lr_final
    assert rates == pytest.approx([2e-3, 2e-3, 2e-3, 1.05e-3, 1e-4], rel=1e-9)
    method = get_method("flam")
    constant = json.loads(method.config_json(_layout(), TINY))
    assert method.fingerprint(method.config_json(_layout(), decayed)) == method.fingerprint(json.dumps(constant))
    for key in ("lr_decay_updates", "lr_final", "clip_frames"):  # a run directory from before the fields resumes too
        constant["flam"].pop(key)
    assert method.fingerprint(json.dumps(constant)) == method.fingerprint(method.config_json(_layout(), TINY))


def test_only_multigrid_layouts_and_sound_settings_are_taken() -> None:
    assert multigrid_geometry(_layout()) == (2, 4)
    chemical = FactorLayout.from_spec(ChemicalPixelsEnv(graph="chain", num_objects=2).env_spec())
    with pytest.raises(ValueError, match="MultiGrid-agents states only"):
        multigrid_geometry(chemical)
    for bad in ({"slot_dim": 6}, {"lr": 0.0}, {"beta_kl": -1.0}, {"beta_kl": math.nan}, {"ae_updates": -1},
                {"aggregator": "sum"}, {"mask_prior": "always"}, {"horizon": 0}, {"mask_binding": -1.0},
                {"lr_decay_updates": -1}, {"lr_final": 0.0}, {"clip_frames": 1},
                {"mask_binding": 1.0, "mask_prior": "none"}):
        with pytest.raises(ValueError):
            FLAMRunConfig(**bad)
    with pytest.raises(ValueError, match="--flam-mask-binding 0 with --flam-mask-prior none"):
        FLAMRunConfig(mask_prior="none")  # the binding term is on by default: the error says what to set
    assert FLAMRunConfig(mask_prior="none", mask_binding=0.0).mask_binding == 0.0
    method = get_method("flam")
    assert method.envs == ("multigrid-agents", "multigrid-agents-correlated") and method.latent_actions is not None


def test_token_labels_take_one_label_per_grid_cell() -> None:
    env = _env()
    frames, labels = env.render_positions(np.array([[[0, 0], [3, 2]]]))
    tokens = token_labels(labels)
    assert tokens.shape == (1, 16) and tokens[0, 0] == 1 and tokens[0, 2 * 4 + 3] == 2 and int(tokens.sum()) == 3


def test_the_annealed_prior_needs_a_slot_per_agent_and_the_background() -> None:
    correlated = MultiGridAgentsEnv(num_agents=3, grid_size=4, correlated=True)
    layout = FactorLayout.from_spec(correlated.env_spec())
    few = FLAMRunConfig(**{**TINY.__dict__, "num_slots": 3})  # K = 2 + 1 for 3 agents, two acting alike
    with pytest.raises(ValueError, match="--flam-num-slots must be 0 or >= 4, got 3"):
        check_layout(layout, few)
    with pytest.raises(ValueError, match="--flam-num-slots must be 0 or >= 4"):
        FLAMTrainer(layout, few, seed=0)  # the model refuses them too, not only a run's start
    for fine in ({"num_slots": 0}, {"num_slots": 4}, {"num_slots": 3, "mask_prior": "none", "mask_binding": 0.0}):
        check_layout(layout, FLAMRunConfig(**{**TINY.__dict__, **fine}))
    # without a prior, fewer slots than segments train (the correlated variant's test: K = agents - 1 + 1)
    trainer = FLAMTrainer(layout, FLAMRunConfig(**{**TINY.__dict__, "num_slots": 3, "mask_prior": "none",
                                                   "mask_binding": 0.0}), seed=0)
    videos = record_videos(correlated, 2, 2, seed=0)
    positions = torch.from_numpy(videos["positions"].reshape(2, 3, 6).astype(np.float32))
    for _ in range(3):
        stats = trainer.update(positions[:, :-1].reshape(4, 6), torch.zeros(4, 1), positions[:, 1:].reshape(4, 6))
    assert stats["phase"] == 1.0 and math.isfinite(stats["loss"])
