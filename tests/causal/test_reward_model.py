"""The reward predictor of eq. 3.5 fits a known reward from the kept and goal factors only."""
from __future__ import annotations

import numpy as np
import torch

from causal.factored import FactorLayout
from causal.reward_model import RewardModel, RewardModelConfig

# Two colours, a distractor position, two provided goal colours; action sets nothing here.
LAYOUT = FactorLayout(
    names=("c0", "c1", "x", "g0", "g1"), kinds=("categorical", "categorical", "continuous", "categorical", "categorical"),
    sizes=(3, 3, 1, 3, 3), locs=(0.0,) * 5, scales=(1.0,) * 5, action_kind="categorical", action_size=2,
)
INPUTS = (0, 1, 3, 4)  # kept colours + goal factors; the distractor x is not an input


def batch(rng: np.random.Generator, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    s = rng.integers(0, 3, (n, 5)).astype(np.float32)
    s[:, 2] = rng.normal(size=n) * 100
    a = rng.integers(0, 2, (n, 1)).astype(np.float32)
    reward = ((s[:, 0] == s[:, 3]).astype(np.float32) + (s[:, 1] == s[:, 4])) / 2 + 0.25 * a[:, 0]
    return torch.from_numpy(s), torch.from_numpy(a), torch.from_numpy(reward)


def test_reward_model_fits_a_match_reward_and_ignores_non_inputs() -> None:
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    model = RewardModel(LAYOUT, INPUTS, RewardModelConfig(lr=1e-2), seed=0)
    assert model.cfg.hidden == (32, 32) and RewardModelConfig().lr == 3e-4
    losses = [model.fit_step(*batch(rng, 128)) for _ in range(400)]
    state, action, reward = batch(rng, 2000)
    assert model.loss(state, action, reward).item() < 0.05, losses[-5:]
    moved = state.clone()
    moved[:, 2] = -moved[:, 2]
    torch.testing.assert_close(model(state, action), model(moved, action))
    assert not model(state, action).requires_grad


def test_reward_model_state_round_trips() -> None:
    rng = np.random.default_rng(1)
    a, b = RewardModel(LAYOUT, INPUTS, seed=0), RewardModel(LAYOUT, INPUTS, seed=5)
    a.fit_step(*batch(rng, 16))
    b.load_state_dict(a.state_dict())
    state, action, _ = batch(rng, 8)
    torch.testing.assert_close(a(state, action), b(state, action))
