"""CBM's reward CMI (issue 19): on a deterministic reward that reads 2 of 6 factors, the drop-one
masks' CMI must single out exactly those 2 at the 0.01-nat threshold. The earlier per-mask variance
(``0.5 log(MSE_{-i} / MSE)``) fails this on the same trained models in seeds 0 and 2: once the full
mask fits the reward almost exactly, the log ratio of two small residual MSEs scores every input the
reward ignores at 0.14-0.36 nats."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.cbm_config import CBMConfig
from causal.cbm_reward import CausalRewardModel
from causal.factored import FactorLayout

KINDS = ("categorical", "continuous", "categorical", "continuous", "categorical", "continuous")
SIZES = (3, 1, 3, 1, 3, 1)


def _layout() -> FactorLayout:
    n = len(KINDS)
    return FactorLayout(tuple(f"f{k}" for k in range(n)), KINDS, SIZES, (0.0,) * n, (1.0,) * n, "categorical", 4)


def _batch(g: torch.Generator, b: int) -> tuple[torch.Tensor, ...]:
    """Match in miniature: reward 1 when colour f0 equals goal f2, else 0; f1, f3-f5 and the action
    are read by nothing."""
    columns = [torch.randint(0, size, (b,), generator=g).float() if kind == "categorical"
               else torch.rand(b, generator=g) * 2 - 1 for kind, size in zip(KINDS, SIZES)]
    state = torch.stack(columns, dim=1)
    action = torch.randint(0, 4, (b, 1), generator=g).float()
    return state, action, (state[:, 0] == state[:, 2]).float()


def _train(seed: int, updates: int) -> tuple[CausalRewardModel, torch.Generator]:
    torch.manual_seed(seed)
    model, g = CausalRewardModel(_layout(), CBMConfig(reward_hidden=64)), torch.Generator().manual_seed(seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(updates):
        loss = model.squared_errors(*_batch(g, 64)).mean(dim=1).sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return model, g


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reward_cmi_finds_exactly_the_two_parents(seed: int) -> None:
    model, g = _train(seed, 600)
    state, action, reward = _batch(g, 2000)
    cmi = model.cmi(state, action, reward).numpy()
    with torch.no_grad():
        errors = model.squared_errors(state, action, reward).mean(dim=1)
    assert float(errors[0]) < 0.05 * float(reward.var()), errors  # the full mask fits the reward
    parents = cmi >= CBMConfig().reward_threshold
    assert parents.tolist() == [True, False, True, False, False, False, False], np.round(cmi, 4)
    assert cmi[[0, 2]].min() > 0.1, np.round(cmi, 4)  # far from the threshold, not just above it


def test_reward_cmi_is_the_shared_variance_likelihood_ratio() -> None:
    """The CMI is ``(MSE_{-i} - MSE) / (2 Var(r))``: the mean log-likelihood ratio of two Gaussians with
    the reward's variance, computed here from the predictions directly; its standard error the spread of
    the per-sample ratios over ``sqrt(n)``."""
    model, g = _train(3, 50)
    state, action, reward = _batch(g, 700)
    variance = reward.double().var()
    with torch.no_grad():
        means = model.means(state, action, model.masks).double()

    def log_normal(mean: torch.Tensor) -> torch.Tensor:
        return -0.5 * (reward.double() - mean).square() / variance

    ratios = log_normal(means[:1]) - log_normal(means[1:])  # [I, B]
    cmi, stderr = model.cmi_with_stderr(state, action, reward, chunk=256)
    np.testing.assert_allclose(cmi.numpy(), ratios.mean(dim=1).numpy(), rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(stderr.numpy(), (ratios.std(dim=1) / 700 ** 0.5).numpy(), rtol=1e-4, atol=1e-7)
