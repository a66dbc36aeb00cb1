"""Dyn-O's slot world model (eq. 7.2): shapes, slot-permutation equivariance, the matched monolithic
baseline, temporal slot alignment, and the PSNR/SSIM helpers on closed-form cases."""
from __future__ import annotations

import math

import pytest
import torch

from causal.slot_world_model import (
    MonolithicWorldModel,
    SlotWorldModel,
    WorldModelConfig,
    align_slots,
    monolithic_width,
    parameter_count,
    psnr,
    ssim,
    world_model_loss,
)

torch.set_num_threads(1)
B, T, K, D, ACTIONS = 3, 4, 5, 8, 6


def _model() -> SlotWorldModel:
    torch.manual_seed(0)
    return SlotWorldModel(D, ACTIONS, WorldModelConfig(hidden=16, heads=2)).eval()


def test_shapes_of_a_step_a_sequence_and_a_rollout() -> None:
    model = _model()
    slots, actions = torch.randn(B, T, K, D), torch.randint(ACTIONS, (B, T))
    step = model.step(slots[:, 0], actions[:, 0], model.initial_hidden(slots[:, 0]))
    assert step.next_slots.shape == (B, K, D) and step.hidden.shape == (B, K, 16)
    assert step.reward.shape == (B,) and step.termination_logit.shape == (B,)
    predicted, reward, termination = model(slots, actions)
    assert predicted.shape == (B, T, K, D) and reward.shape == (B, T) and termination.shape == (B, T)
    assert model.rollout(slots[:, 0], torch.randint(ACTIONS, (B, 20))).shape == (B, 20, K, D)


def test_permuting_the_slots_permutes_the_predictions_and_leaves_reward_and_termination() -> None:
    model = _model()
    slots, actions = torch.randn(B, T, K, D), torch.randint(ACTIONS, (B, T))
    order = torch.tensor([3, 0, 4, 1, 2])
    predicted, reward, termination = model(slots, actions)
    permuted, reward_p, termination_p = model(slots[:, :, order], actions)
    torch.testing.assert_close(permuted, predicted[:, :, order], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(reward_p, reward, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(termination_p, termination, rtol=1e-5, atol=1e-5)
    rolled = model.rollout(slots[:, 0], actions)
    torch.testing.assert_close(model.rollout(slots[:, 0, order], actions), rolled[:, :, order], rtol=1e-5, atol=1e-5)


def test_the_action_and_the_other_slots_reach_each_prediction() -> None:
    model = _model()
    slots = torch.randn(1, 1, K, D)
    base, _, _ = model(slots, torch.tensor([[0]]))
    other_action, _, _ = model(slots, torch.tensor([[1]]))
    assert (other_action - base).abs().amax(dim=-1).min() > 1e-4, "every slot's prediction reads the action"
    moved = slots.clone()
    moved[0, 0, 0] += torch.randn(D)
    changed, _, _ = model(moved, torch.tensor([[0]]))
    assert (changed - base)[0, 0, 1:].abs().amax(dim=-1).min() > 1e-5, "slot 0 reaches the others (attention)"


def test_the_loss_adds_reward_and_termination_terms_only_when_given() -> None:
    predicted = (torch.zeros(2, 3, 4), torch.zeros(2, 3), torch.zeros(2, 3))
    target = torch.ones(2, 3, 4)
    assert float(world_model_loss(predicted, target)) == pytest.approx(1.0)
    with_reward = world_model_loss(predicted, target, rewards=torch.full((2, 3), 2.0))
    assert float(with_reward) == pytest.approx(5.0)
    with_both = world_model_loss(predicted, target, torch.zeros(2, 3), torch.ones(2, 3))
    assert float(with_both) == pytest.approx(1.0 + math.log(2.0), rel=1e-6)


def test_the_monolithic_baseline_is_sized_to_match_the_slot_model() -> None:
    target = parameter_count(_model())
    width = monolithic_width(64, ACTIONS, target)
    mono = MonolithicWorldModel(64, ACTIONS, width)
    assert abs(parameter_count(mono) - target) <= 0.05 * target
    assert abs(parameter_count(MonolithicWorldModel(64, ACTIONS, width + 1)) - target) >= abs(parameter_count(mono) - target)
    latents, actions = torch.randn(B, T, 64), torch.randint(ACTIONS, (B, T))
    assert mono(latents, actions)[0].shape == (B, T, 64) and mono.rollout(latents[:, 0], actions).shape == (B, T, 64)


def test_a_rollout_after_context_frames_continues_the_teacher_forced_sequence() -> None:
    """observe + rollout: the first open-loop step after C context frames is the teacher-forced
    prediction at frame C, for both models (so context frames reach the rollout through the hidden
    state), and without context the rollout is unchanged."""
    context = 2
    model = _model()
    slots, actions = torch.randn(B, T, K, D), torch.randint(ACTIONS, (B, T))
    teacher, _, _ = model(slots, actions)
    hidden = model.observe(slots[:, :context], actions[:, :context])
    rolled = model.rollout(slots[:, context], actions[:, context:], hidden)
    torch.testing.assert_close(rolled[:, 0], teacher[:, context], rtol=1e-5, atol=1e-5)
    assert (model.rollout(slots[:, context], actions[:, context:])[:, 0] - rolled[:, 0]).abs().max() > 1e-4
    torch.testing.assert_close(model.rollout(slots[:, 0], actions), model.rollout(slots[:, 0], actions, None))
    torch.manual_seed(0)
    mono = MonolithicWorldModel(64, ACTIONS, 16).eval()
    latents = torch.randn(B, T, 64)
    teacher_mono, _, _ = mono(latents, actions)
    rolled_mono = mono.rollout(latents[:, context], actions[:, context:], mono.observe(latents[:, :context], actions[:, :context]))
    torch.testing.assert_close(rolled_mono[:, 0], teacher_mono[:, context], rtol=1e-5, atol=1e-5)


def test_align_slots_undoes_a_per_frame_permutation() -> None:
    torch.manual_seed(1)
    masks = torch.eye(K)[None, None].expand(2, T, K, K).clone()
    slots = torch.randn(2, 1, K, D).expand(2, T, K, D).clone()
    for t in range(1, T):
        order = torch.randperm(K)
        slots[:, t], masks[:, t] = slots[:, t, order], masks[:, t, order]
    aligned, aligned_masks = align_slots(slots, masks)
    torch.testing.assert_close(aligned, slots[:, :1].expand_as(slots))
    torch.testing.assert_close(aligned_masks, torch.eye(K)[None, None].expand_as(masks))


def test_psnr_of_a_uniform_error_and_of_identical_images() -> None:
    target = torch.rand(2, 3, 8, 8) * 0.5
    assert psnr(target + 0.1, target).tolist() == pytest.approx([20.0, 20.0], abs=1e-4)
    assert psnr(target + 0.01, target).tolist() == pytest.approx([40.0, 40.0], abs=1e-3)
    assert psnr(target, target).tolist() == pytest.approx([100.0, 100.0])


def test_ssim_of_identical_constant_and_noisy_images() -> None:
    torch.manual_seed(2)
    image = torch.rand(2, 3, 16, 16)
    assert ssim(image, image).tolist() == pytest.approx([1.0, 1.0], abs=1e-6)
    a, b, c1 = 0.2, 0.6, 0.01 ** 2
    constant = ssim(torch.full((1, 3, 16, 16), a), torch.full((1, 3, 16, 16), b))
    assert float(constant) == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-5)
    mild, strong = (ssim((image + s * torch.randn_like(image)).clamp(0, 1), image) for s in (0.05, 0.3))
    assert (strong < mild).all() and (mild < 1.0).all()
