"""Dyn-O's static/dynamic split (eqs. 7.3-7.5): the time-invariance and InfoNCE terms on closed-form
cases, the stop-gradient and the critic's part in each loss, LeCam's running means, and the probe."""
from __future__ import annotations

import math

import pytest
import torch

from causal.slot_split import SplitConfig, StaticDynamicSplit, bins, info_nce, linear_probe, time_invariance

torch.set_num_threads(1)


def test_time_invariance_is_zero_for_constant_features_and_the_mean_pair_distance_otherwise() -> None:
    constant = torch.randn(2, 1, 3, 4).expand(2, 5, 3, 4)
    assert float(time_invariance(constant)) == pytest.approx(0.0, abs=1e-9)
    two = torch.zeros(1, 2, 1, 2)
    two[0, 1, 0] = torch.tensor([3.0, 4.0])
    assert float(time_invariance(two)) == pytest.approx(25.0)


def test_info_nce_is_low_for_distinct_constant_slots_and_log_n_when_collapsed() -> None:
    b, t, k = 2, 3, 4
    collapsed = torch.ones(b, t, k, 8)
    candidates = b * t * k - (t - 1)
    assert float(info_nce(collapsed, 0.1)) == pytest.approx(math.log(candidates), rel=1e-5)
    distinct = torch.eye(8)[: b * k].view(b, 1, k, 8).expand(b, t, k, 8)
    assert float(info_nce(distinct, 0.1)) < 1e-3


def test_reconstruction_does_not_train_the_static_map_and_the_critic_loss_trains_only_the_critic() -> None:
    torch.manual_seed(0)
    split = StaticDynamicSplit(6, SplitConfig(static_dim=4, dynamic_dim=4, hidden=8))
    losses = split.losses(torch.randn(2, 3, 4, 6))
    assert all(torch.isfinite(v) for v in losses)
    losses.dynamic.backward(retain_graph=True)
    assert all(p.grad is None for p in split.static.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in split.dynamic.parameters())
    split.zero_grad(set_to_none=True)
    losses.critic.backward()
    assert all(p.grad is None for name, p in split.named_parameters() if not name.startswith("critic."))


def test_lecam_running_means_move_only_in_training() -> None:
    torch.manual_seed(0)
    split = StaticDynamicSplit(6, SplitConfig(static_dim=4, dynamic_dim=4, hidden=8, lecam_decay=0.5))
    split.losses(torch.randn(2, 3, 4, 6))
    moved = (float(split.mean_same), float(split.mean_other))
    assert moved != (0.0, 0.0)
    split.eval()
    split.losses(torch.randn(2, 3, 4, 6))
    assert (float(split.mean_same), float(split.mean_other)) == moved


def test_the_probe_separates_separable_classes_and_bins_cover_the_range() -> None:
    torch.manual_seed(0)
    labels = torch.randint(3, (300,))
    inputs = torch.nn.functional.one_hot(labels, 3).float() * 5 + 0.1 * torch.randn(300, 3)
    assert linear_probe(inputs[:200], labels[:200], inputs[200:], labels[200:], 3) == 1.0
    assert linear_probe(torch.randn(200, 3), labels[:200], torch.randn(100, 3), labels[200:], 3) < 0.6
    assert bins(torch.tensor([0.0, 0.05, 0.5, 0.99, 1.0])).tolist() == [0, 0, 5, 9, 9]


@pytest.mark.parametrize("bad", [{"critic_steps": 0}, {"temperature": 0.0}, {"lecam_decay": 1.0}, {"disentangle_weight": -1.0}])
def test_split_config_rejects_bad_values(bad: dict) -> None:
    with pytest.raises(ValueError):
        SplitConfig(**bad)


def test_a_spectrally_normalised_critic_is_1_lipschitz_layer_by_layer() -> None:
    """``critic_spectral_norm``: each of the critic's linear maps has spectral norm ~1 once its power
    iteration has run (training mode), so the critic is 1-Lipschitz, as a Wasserstein critic must be."""
    torch.manual_seed(0)
    split = StaticDynamicSplit(6, SplitConfig(static_dim=4, dynamic_dim=4, hidden=8, critic_spectral_norm=True))
    with torch.no_grad():
        for layer in split.critic:
            if isinstance(layer, torch.nn.Linear):
                layer.parametrizations.weight.original.mul_(50.0)  # far from 1 before normalisation
    for _ in range(30):
        split.losses(torch.randn(2, 3, 4, 6))
    norms = [float(torch.linalg.matrix_norm(layer.weight.detach(), 2)) for layer in split.critic if isinstance(layer, torch.nn.Linear)]
    assert len(norms) == 3 and all(n == pytest.approx(1.0, abs=1e-2) for n in norms)


def test_a_standardising_critic_sees_a_shrunk_channel_at_full_scale() -> None:
    """``critic_standardise``: scaling one channel of v (by any positive factor) leaves the critic's
    scores unchanged, so the features cannot hide static information from it by shrinking it; the
    plain critic's scores change."""
    torch.manual_seed(0)
    static, dynamic = torch.randn(2, 3, 4, 4), torch.randn(2, 3, 4, 4)
    shrunk = dynamic.clone()
    shrunk[..., 1] *= 1e-2
    for standardise in (True, False):
        split = StaticDynamicSplit(6, SplitConfig(static_dim=4, dynamic_dim=4, hidden=8, critic_standardise=standardise))
        with torch.no_grad():
            before, after = split.disc(static, dynamic), split.disc(static, shrunk)
        if standardise:
            torch.testing.assert_close(after, before, rtol=1e-3, atol=1e-3 * float(before.abs().max()))
        else:
            assert not torch.allclose(after, before, rtol=1e-3)
