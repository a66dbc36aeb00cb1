"""Behaviour cloning from pseudo-labels (eq. 8.7): the action decoder, the frame policy, the classifier
loop and the policy evaluation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.flam_bc import ActionDecoder, ClassifierTraining, FramePolicy, evaluate_policy, fit_classifier, predict, pseudo_labels
from envs.sprites import SpritesEnv

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_the_decoder_recovers_actions_coded_in_latents_from_few_labels() -> None:
    generator = torch.Generator().manual_seed(0)
    actions = torch.randint(5, (2000,), generator=generator)
    # latent actions of 3 slots x 4 dims: slot 1 codes the action (scaled, offset), the rest is noise
    latents = torch.randn(2000, 3, 4, generator=generator)
    latents[:, 1, :] = 3.0 * torch.nn.functional.one_hot(actions, 5)[:, :4].float() - 7.0 + 0.1 * latents[:, 1, :]
    latents[actions == 4, 1, 0] = 9.0
    labelled = torch.arange(200)
    torch.manual_seed(0)
    labels, accuracy = pseudo_labels(ActionDecoder(12, 5), latents.flatten(1), labelled, actions,
                                     ClassifierTraining(updates=300, batch_size=64, lr=3e-3), seed=0)
    assert labels.shape == actions.shape and labels.dtype == torch.int64
    assert accuracy > 0.97
    # unlabelled accuracy is scored on rows not labelled: labelling every row leaves none
    _, none = pseudo_labels(ActionDecoder(12, 5), latents.flatten(1)[:50], torch.arange(50), actions[:50],
                            ClassifierTraining(updates=5), seed=0)
    assert np.isnan(none)


def test_the_frame_policy_learns_an_action_shown_in_the_frame() -> None:
    generator = torch.Generator().manual_seed(1)
    actions = torch.randint(5, (500,), generator=generator)
    frames = torch.randint(0, 60, (500, 32, 32, 3), dtype=torch.uint8, generator=generator)
    for a in range(5):  # a bright square whose column tells the action
        frames[actions == a, 12:20, 6 * a:6 * a + 6] = 255
    torch.manual_seed(0)
    policy = FramePolicy(5, 32)
    assert policy(frames[:7]).shape == (7, 5)
    fit_classifier(policy, frames[:400], actions[:400], ClassifierTraining(updates=300, batch_size=64, lr=2e-3), seed=0)
    assert float((predict(policy, frames[400:]) == actions[400:]).float().mean()) > 0.95
    assert not policy.training


def test_fit_classifier_refuses_mismatched_data() -> None:
    with pytest.raises(ValueError, match="as many targets"):
        fit_classifier(ActionDecoder(2, 2), torch.zeros(3, 2), torch.zeros(2, dtype=torch.int64), ClassifierTraining())
    with pytest.raises(ValueError, match="positive"):
        ClassifierTraining(updates=0)


def test_evaluate_policy_is_seeded_and_scores_returns() -> None:
    make_env = lambda: SpritesEnv(num_fish=2, episode_length=30)  # noqa: E731
    torch.manual_seed(0)
    policy = FramePolicy(5, 32)
    first, second = (evaluate_policy(policy, make_env, 3, seed=5) for _ in range(2))
    assert first == second and first["episodes"] == 3 and 0.0 <= first["success_rate"] <= 1.0
    stay = evaluate_policy(None, make_env, 2, seed=5, act=lambda env: 0)
    assert stay["return_std"] >= 0.0 and np.isfinite(stay["return_mean"])
