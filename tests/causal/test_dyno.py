"""Dyn-O as a trainer (chapter 7): its phases in order (autoencoder, slots, world model), what each
phase trains and freezes, the matched slot loss, checkpoint round trips, and the FG-ARI scorer."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from causal.dyno import DynOConfig, DynOTrainer, SlotScores, chemical_geometry, matched_slot_mse, model_from_config
from causal.factored import FactorLayout
from causal.methods import get_method
from envs.chemical_pixels import ChemicalPixelsEnv

torch.set_num_threads(1)
TINY = DynOConfig(frame_size=16, slot_dim=8, feature_dim=4, iterations=2, ae_updates=2, slot_updates=2,
                  wm_hidden=8, batch_size=4)


def _env() -> ChemicalPixelsEnv:
    return ChemicalPixelsEnv(graph="chain", num_objects=2, frame_size=16)


def _batch(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    env = _env()
    env.reset(seed=seed)
    states = env.sample_states(8)
    actions = env.np_random.integers(0, int(env.action_space.n), size=(4, 1)).astype(np.float32)
    return (torch.from_numpy(states[:4]), torch.from_numpy(actions), torch.from_numpy(states[4:]))


def _layout() -> FactorLayout:
    return FactorLayout.from_spec(_env().env_spec())


def _params(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def _changed(before: list[torch.Tensor], module: torch.nn.Module) -> bool:
    return any(not torch.equal(a, b) for a, b in zip(before, module.parameters()))


def test_phases_train_in_order_and_freeze_what_is_done() -> None:
    trainer = DynOTrainer(_layout(), TINY, seed=0)
    slots, world = trainer.model.slots, trainer.model.world
    phases = []
    for u in range(6):
        ae, attention, wm = _params(slots.autoencoder), _params(slots.slot_attention), _params(world)
        stats = trainer.update(*_batch(u))
        phases.append(int(stats["phase"]))
        assert _changed(ae, slots.autoencoder) == (u < 2)
        assert _changed(attention, slots.slot_attention) == (2 <= u < 4)
        assert _changed(wm, world) == (u >= 4)
        assert all(np.isfinite(v) for v in stats.values())
    assert phases == [0, 0, 1, 1, 2, 2] and trainer.updates == 6
    assert {"world_model_mse", "phase"} <= set(stats)


def test_a_checkpoint_resumes_the_same_training() -> None:
    first = DynOTrainer(_layout(), TINY, seed=0)
    for u in range(3):
        first.update(*_batch(u))
    second = DynOTrainer(_layout(), TINY, seed=1)
    second.load_state_dict(first.state_dict())
    assert second.phase == "slots" and not any(p.requires_grad for p in second.model.slots.autoencoder.parameters())
    a, b = first.update(*_batch(9)), second.update(*_batch(9))
    assert a == pytest.approx(b, rel=1e-6)
    for name, value in first.model.state_dict().items():
        torch.testing.assert_close(second.model.state_dict()[name], value)


def test_the_config_json_rebuilds_the_model_by_name() -> None:
    trainer = DynOTrainer(_layout(), TINY, seed=0)
    data = json.loads(trainer.config_json())
    assert data["model"] == "dyno" and data["dyno"] == dataclasses.asdict(TINY)
    rebuilt = get_method("dyno").model_from_config(data)
    assert set(dict(rebuilt.named_parameters())) == set(dict(trainer.model.named_parameters()))
    assert type(model_from_config(data)) is type(rebuilt)


def test_the_matched_loss_ignores_the_slot_order() -> None:
    torch.manual_seed(0)
    target = torch.randn(3, 5, 4)
    shuffled = target[:, torch.tensor([2, 0, 4, 3, 1])]
    assert float(matched_slot_mse(shuffled, target)) == pytest.approx(0.0, abs=1e-12)
    noisy = shuffled + 0.1
    assert float(matched_slot_mse(noisy, target)) == pytest.approx(0.01, rel=1e-5)
    assert float(torch.nn.functional.mse_loss(shuffled, target)) > 0.5


def test_only_chemical_layouts_can_be_rendered_and_settings_are_checked() -> None:
    assert chemical_geometry(_layout()) == (2, 5)
    other = dataclasses.replace(_layout(), names=("a", "b", "c", "d", "e", "f"))
    with pytest.raises(ValueError, match="Chemical"):
        chemical_geometry(other)
    with pytest.raises(ValueError, match="positive"):
        DynOConfig(batch_size=0)
    with pytest.raises(ValueError, match="mask_prior"):
        DynOConfig(mask_prior="sometimes")
    with pytest.raises(ValueError, match="token_mask"):
        DynOConfig(token_mask="some")
    with pytest.raises(ValueError, match="mask_binding"):
        DynOConfig(mask_binding=-1.0)


def test_two_tone_frames_and_the_binding_term_reach_the_slot_phase() -> None:
    """The run's Table 7.1 setting: frames of two-part objects, masks that give a token to its objects
    only, and the binding term, which the slot phase then reports."""
    config = dataclasses.replace(TINY, ae_updates=0, two_tone=True, token_mask="objects", mask_binding=1.0)
    trainer = DynOTrainer(_layout(), config, seed=0)
    slots = trainer.model.slots.config
    assert (slots.token_mask, slots.mask_binding) == ("objects", 1.0) and trainer.render.two_tone
    state = _batch()[0]
    plain, _ = DynOTrainer(_layout(), TINY, seed=0).frames(state)
    toned, labels = trainer.frames(state)
    assert not torch.equal(plain, toned) and torch.equal(plain[labels == 0], toned[labels == 0])
    stats = trainer.update(*_batch())
    assert stats["phase"] == 1.0 and stats["mask_binding_ce"] > 0.0
    assert model_from_config(json.loads(trainer.config_json())).renderer().two_tone


def test_the_slot_scorer_gives_fg_ari_of_unseen_frames() -> None:
    trainer = DynOTrainer(_layout(), TINY, seed=0)
    scores = SlotScores(frames=16).scores(trainer.model, _env().env_spec())
    assert -1.0 <= scores["fg_ari"] <= 1.0 and scores["frames"] == 16 and scores["num_slots"] == 3
    again = SlotScores(frames=16).scores(trainer.model, _env().env_spec())
    assert again["fg_ari"] == scores["fg_ari"]
