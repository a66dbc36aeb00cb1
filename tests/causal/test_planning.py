"""CEM finds known optima; CDL rollouts respect the parents mask, the abstraction and extra columns."""
from __future__ import annotations

import torch

from causal.cdl import CDLConfig, CDLModel
from causal.factored import FactorCodec, FactorLayout
from causal.planning import CEMConfig, CEMPlanner, cdl_rollout_step, next_state_from_outputs, predicted_next_state
from causal.rl.base import ActionSpec

LAYOUT = FactorLayout(
    names=("k", "x", "m"), kinds=("categorical", "continuous", "categorical"), sizes=(3, 1, 4),
    locs=(0.0, 1.0, 0.0), scales=(1.0, 2.0, 1.0), action_kind="categorical", action_size=3,
)


def test_cem_defaults_are_the_reference_search() -> None:
    assert CEMConfig() == CEMConfig(horizon=3, iterations=5, population=64, elites=32)


def test_cem_continuous_finds_the_optimum_of_a_quadratic_under_linear_dynamics() -> None:
    """s' = s + a, r(s, a) = -|s + a - goal|^2: the best first action is goal - s.

    The diagonal belief converges slowly when later steps can undo the first (the coupling here),
    so the test searches wider than the reference's 64/32 x 5.
    """
    goal = torch.tensor([0.5, -0.3])
    planner = CEMPlanner(lambda s, a: s + a, lambda s, a: -(s + a - goal).square().sum(-1),
                         ActionSpec("continuous", 2, (-2.0, -2.0), (2.0, 2.0)),
                         CEMConfig(population=256, elites=32, iterations=10), seed=0)
    starts = torch.tensor([[0.0, 0.0], [1.0, 0.5], [-0.5, -1.0]])
    torch.testing.assert_close(planner.plan(starts), goal - starts, atol=0.05, rtol=0)
    assert planner.plan(starts[1]).shape == (2,)


def test_cem_continuous_stays_within_bounds() -> None:
    planner = CEMPlanner(lambda s, a: s, lambda s, a: a.sum(-1), ActionSpec("continuous", 1, (-1.0,), (0.25,)))
    assert 0.2 <= planner.plan(torch.zeros(1, 1)).item() <= 0.25


def test_cem_categorical_finds_the_optimal_first_action() -> None:
    """Counter s' = s + (a - 2), reward -|s' - 4|: the first action heads for 4 as fast as it can."""
    step = lambda s, a: s + (a - 2)  # noqa: E731
    reward = lambda s, a: -(step(s, a) - 4).abs().sum(-1)  # noqa: E731
    planner = CEMPlanner(step, reward, ActionSpec("categorical", 5), seed=0)
    assert planner.plan(torch.zeros(1)).item() == 4
    assert planner.plan(torch.tensor([[0.0], [4.0], [5.0], [8.0]])).tolist() == [4, 2, 1, 0]


def _model() -> CDLModel:
    torch.manual_seed(0)
    return CDLModel(LAYOUT, CDLConfig(feature_hidden=8, feature_dim=8, predictor_hidden=8))


def _states(n: int, extra: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    k, m = torch.randint(0, 3, (n, 1), generator=g), torch.randint(0, 4, (n, 1), generator=g)
    return torch.cat([k.float(), torch.randn(n, 1, generator=g), m.float(), torch.randn(n, extra, generator=g)], 1)


def test_causal_prediction_ignores_non_parents() -> None:
    model, states = _model(), _states(32)
    actions = torch.randint(0, 3, (32, 1)).float()
    parents = torch.tensor([[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0]], dtype=torch.bool)
    changed = states.clone()
    changed[:, 1] += 5.0  # x is no parent of k or m
    a, b = (predicted_next_state(model, s, actions, parents) for s in (states, changed))
    torch.testing.assert_close(a[:, [0, 2]], b[:, [0, 2]])
    assert not torch.allclose(a[:, 1], b[:, 1])
    assert set(a[:, 0].tolist()) <= {0.0, 1.0, 2.0} and set(a[:, 2].tolist()) <= {0.0, 1.0, 2.0, 3.0}


def test_rollout_step_holds_unkept_factors_and_carries_extra_columns() -> None:
    model, states = _model(), _states(16, extra=2)
    actions = torch.zeros(16, 1)
    step = cdl_rollout_step(model, torch.ones(3, 4, dtype=torch.bool), factors=[0])
    nxt = step(states, actions)
    torch.testing.assert_close(nxt[:, 1:], states[:, 1:])
    full = cdl_rollout_step(model, torch.ones(3, 4, dtype=torch.bool))(states, actions)
    torch.testing.assert_close(full[:, 3:], states[:, 3:])
    torch.testing.assert_close(full[:, 0], nxt[:, 0])


def test_next_state_from_outputs_takes_argmax_and_scaled_mean_residual() -> None:
    codec = FactorCodec(LAYOUT)
    out = torch.zeros(3, 1, LAYOUT.head_width)
    out[0, 0, :4] = torch.tensor([0.0, 0.0, 1.0, 9.0])  # class 3 does not exist for k (size 3)
    out[1, 0, 0] = 0.25  # mean residual in normalised units (scale 2)
    out[2, 0, :4] = torch.tensor([0.0, 5.0, 0.0, 0.0])
    nxt = next_state_from_outputs(codec, out, torch.tensor([[0.0, 3.0, 0.0, 7.0]]))
    torch.testing.assert_close(nxt, torch.tensor([[2.0, 3.5, 1.0, 7.0]]))
    # a next value (CDLConfig.target "next") is location + scale x mean, whatever the state holds
    as_value = next_state_from_outputs(codec, out, torch.tensor([[0.0, 3.0, 0.0, 7.0]]), target="next")
    torch.testing.assert_close(as_value, torch.tensor([[2.0, 1.5, 1.0, 7.0]]))
    sampled = next_state_from_outputs(codec, out.expand(-1, 200, -1), torch.zeros(200, 4), sample=True,
                                      generator=torch.Generator().manual_seed(0))
    assert sampled[:, 0].max() <= 2 and sampled[:, 1].std() > 0
