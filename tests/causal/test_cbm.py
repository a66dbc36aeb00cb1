"""CBM (ch. 4): the importance-weighted CMI estimator against closed forms, the candidate-gradient
penalty against autograd, the minimal abstraction on hand-built graphs, and small models that learn
the edges (and the reward's parents) they should."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from causal.abstraction import abstraction_accuracy, cdl_abstraction, minimal_abstraction, reward_ancestors
from causal.cbm import CBMTrainer, model_from_config
from causal.cbm_config import CBMConfig
from causal.cbm_implicit import cmi_from_sums, importance_weighted_cmi
from causal.factored import FactorLayout
from causal.method import export_tensors, import_tensors, task_abstraction
from causal.methods import get_method

torch.set_num_threads(1)  # the machine's two cores are shared: one thread each is faster than contention


def gaussian_log_density(y: torch.Tensor, mean: torch.Tensor, var: float) -> torch.Tensor:
    return -0.5 * (y - mean).square() / var - 0.5 * math.log(2 * math.pi * var)


@pytest.mark.parametrize("sigma", [0.3, 0.5, 1.0])
def test_importance_weighted_cmi_recovers_the_closed_form(sigma: float) -> None:
    """y = x_i + x_rest + sigma * eps with x ~ N(0, 1): CMI(y; x_i | x_rest) = log((1 + s^2) / s^2) / 2.
    With the optimal critics (log-density ratios against the uniform proposal the negatives come from),
    eq. 4.3 with f - psi and w = softmax(psi) tends to it as N grows."""
    g = torch.Generator().manual_seed(0)
    b, n, span = 1_000, 4_096, 8.0
    x_i, x_rest = torch.randn(b, generator=g), torch.randn(b, generator=g)
    y = x_i + x_rest + sigma * torch.randn(b, generator=g)
    negatives = ((torch.arange(n) + torch.rand(n, generator=g)) / n * 2 - 1) * span  # uniform, stratified
    f = lambda v: gaussian_log_density(v, (x_i + x_rest)[:, None], sigma ** 2)  # noqa: E731
    psi = lambda v: gaussian_log_density(v, x_rest[:, None], 1 + sigma ** 2)  # noqa: E731
    estimate = importance_weighted_cmi(f(y[:, None])[:, 0], f(negatives[None]), psi(y[:, None])[:, 0], psi(negatives[None]))
    phi = f(y[:, None])[:, 0] - psi(y[:, None])[:, 0]  # the exact point-wise CMI of these samples
    assert float(estimate.mean()) == pytest.approx(float(phi.mean()), abs=0.02)  # importance sampling's error
    assert float(estimate.mean()) == pytest.approx(0.5 * math.log((1 + sigma ** 2) / sigma ** 2), abs=0.08)
    streamed = cmi_from_sums(f(y[:, None])[:, 0] - psi(y[:, None])[:, 0], torch.logsumexp(f(negatives[None]), -1),
                             torch.logsumexp(psi(negatives[None]), -1), n)
    torch.testing.assert_close(streamed, estimate, atol=1e-4, rtol=1e-4)


def test_importance_weighted_cmi_is_zero_when_the_input_adds_nothing() -> None:
    g = torch.Generator().manual_seed(1)
    scores, label = torch.randn(64, 512, generator=g), torch.randn(64, generator=g)
    zero = importance_weighted_cmi(label, scores, label, scores)  # f == psi: phi = 0 everywhere
    torch.testing.assert_close(zero, torch.zeros(64), atol=1e-5, rtol=0)


def _layout(kinds: tuple[str, ...], sizes: tuple[int, ...], action: tuple[str, int]) -> FactorLayout:
    n = len(kinds)
    return FactorLayout(tuple(f"f{k}" for k in range(n)), kinds, sizes, (0.0,) * n, (1.0,) * n, *action)


def test_candidate_gradient_penalty_equals_autograd() -> None:
    torch.manual_seed(0)
    layout = _layout(("continuous", "continuous", "categorical"), (1, 2, 3), ("continuous", 2))
    model = CBMTrainer(layout, CBMConfig(embed_dim=8, candidate_hidden=16)).model.dynamics
    with torch.no_grad():
        model.delta_high.fill_(1.0), model.delta_low.fill_(-1.0)
    u = torch.randn(2, 2, 3, 8)
    label = torch.randn(2, 3, 2) * model.codec.cont_valid[:, None, :]
    negatives = model.negatives(5) * model.codec.cont_valid[:, None, :]
    closed = model.candidate_grad_sq(u, model.codes(label)[1], model.codes(negatives)[1])
    label.requires_grad_(True), negatives.requires_grad_(True)
    expected = torch.zeros(2, 2, 3)
    for j in range(2):
        for k in range(2):
            for b in range(3):
                f = model.label_scores(u[j : j + 1, k : k + 1, b : b + 1], model.codes(label)[0][j : j + 1, b : b + 1]).sum()
                f = f + model.shared_scores(u[j : j + 1, k : k + 1, b : b + 1], model.codes(negatives)[0][j : j + 1]).sum()
                gl, gn = torch.autograd.grad(f, (label, negatives))
                valid = model.codec.cont_valid[j]
                expected[j, k, b] = (gl[j, b] * valid).square().sum() + (gn[j] * valid).square().sum()
    torch.testing.assert_close(closed, expected, atol=1e-5, rtol=1e-4)


def _graph(n: int, edges: list[tuple[int, int]], action: list[int]) -> np.ndarray:
    """``[n, n + 1]`` with self-edges, ``cause -> effect`` edges and action edges."""
    graph = np.eye(n, n + 1, dtype=np.uint8)
    for cause, effect in edges:
        graph[effect, cause] = 1
    graph[action, n] = 1
    return graph


def test_minimal_abstraction_keeps_the_reward_parents_and_their_ancestors() -> None:
    """sun 0 (nothing moves it), robot 1 (the action), block A 2 and block B 3 (moved by the robot), a
    controllable distractor 4, an uncontrollable one 5. The reward reads the sun and block A."""
    graph = _graph(6, [(1, 2), (1, 3)], action=[1, 4])
    reward = np.array([1, 0, 1, 0, 0, 0, 0], np.uint8)
    assert reward_ancestors(graph, reward) == {0, 1, 2}
    abstraction = minimal_abstraction(graph, reward)
    assert abstraction.kept == (0, 1, 2)
    assert (abstraction.controllable, abstraction.action_relevant, abstraction.action_irrelevant) == ((1, 2), (0,), (3, 4, 5))
    assert cdl_abstraction(graph).kept == (1, 2, 3, 4)  # CDL keeps block B and the distractor, drops the sun
    assert minimal_abstraction(graph, None) == cdl_abstraction(graph)
    assert abstraction_accuracy(cdl_abstraction(graph).kept, abstraction.kept, 6) == pytest.approx(3 / 6)


def test_ancestors_are_followed_through_chains_but_not_through_the_action() -> None:
    graph = _graph(5, [(0, 1), (1, 2), (3, 4)], action=[0, 3])  # a -> 0 -> 1 -> 2, a -> 3 -> 4
    only_action = np.array([0, 0, 0, 0, 0, 1], np.uint8)
    assert minimal_abstraction(graph, only_action).kept == ()
    assert minimal_abstraction(graph, np.array([0, 0, 1, 0, 0, 1], np.uint8)).kept == (0, 1, 2)


def test_task_abstraction_passes_reward_parents_only_to_methods_with_a_reward_graph() -> None:
    graph = _graph(3, [(0, 1)], action=[0, 2])
    reward = np.array([0, 1, 0, 0], np.uint8)
    assert task_abstraction(get_method("cbm"), graph, reward).kept == (0, 1)
    assert task_abstraction(get_method("cdl"), graph, reward).kept == (0, 1, 2)


def _toy_batch(g: torch.Generator, b: int) -> tuple[torch.Tensor, ...]:
    """x' = x + a (deterministic), y' ~ U(-1, 1) (noise), c' = c; reward = c (a categorical factor)."""
    x, y = torch.rand(b, 1, generator=g) * 2 - 1, torch.rand(b, 1, generator=g) * 2 - 1
    c = torch.randint(0, 3, (b, 1), generator=g).float()
    a = torch.rand(b, 1, generator=g) - 0.5
    nxt = torch.cat([x + a, torch.rand(b, 1, generator=g) * 2 - 1, c], dim=1)
    return torch.cat([x, y, c], dim=1), a, nxt, c[:, 0] * 0.5


@pytest.mark.slow
def test_implicit_model_learns_the_edges_the_reward_parents_and_predicts_by_argmax() -> None:
    layout = _layout(("continuous", "continuous", "categorical"), (1, 1, 3), ("continuous", 1))
    cfg = CBMConfig(num_negatives=32, eval_negatives=512, lr=3e-3, batch_size=64, feature_hidden=16,
                    feature_dim=16, predictor_hidden=32, embed_dim=16, candidate_hidden=32)
    trainer, g = CBMTrainer(layout, cfg, seed=0), torch.Generator().manual_seed(0)
    for _ in range(250):
        trainer.update(*_toy_batch(g, 64))
    s, a, nxt, r = _toy_batch(g, 512)
    cmi = trainer.model.dynamics_cmi(s, a, nxt, torch.Generator().manual_seed(1)).numpy()
    # x' reads the action (and x itself: a self-edge, assumed and never scored)
    assert cmi[0, 3] > 0.3, cmi
    off = [cmi[0, 1], cmi[0, 2], *cmi[1, [0, 2, 3]], *cmi[2, [0, 1, 3]]]
    assert max(off) < cfg.cmi_threshold, cmi
    reward = trainer.model.reward_cmi(s, a, r).numpy()
    assert reward[2] > 0.5 and max(reward[[0, 1, 3]]) < cfg.reward_threshold, reward
    predicted = trainer.model.dynamics.predict(s[:256], a[:256])
    error, unchanged = (predicted[:, 0] - nxt[:256, 0]).abs().mean(), (s[:256, 0] - nxt[:256, 0]).abs().mean()
    assert float(error) < 0.6 * float(unchanged), (error, unchanged)
    assert bool((predicted[:, 2] == nxt[:256, 2]).float().mean() > 0.95)


def test_weights_and_checkpoints_carry_the_whole_model() -> None:
    layout = _layout(("continuous", "categorical"), (1, 3), ("categorical", 4))
    cfg = CBMConfig(target="delta", feature_hidden=8, feature_dim=8, predictor_hidden=8, embed_dim=8)  # labels: changes
    trainer = CBMTrainer(layout, cfg, seed=0)
    g = torch.Generator().manual_seed(0)
    s = torch.cat([torch.randn(32, 1, generator=g), torch.randint(0, 3, (32, 1), generator=g).float()], dim=1)
    a = torch.randint(0, 4, (32, 1), generator=g).float()
    for _ in range(3):
        trainer.update(s, a, s + torch.tensor([0.5, 0.0]), torch.zeros(32))
    rebuilt = model_from_config(json.loads(trainer.config_json()))
    import_tensors(rebuilt, export_tensors(trainer.model))  # the delta range travels as (untrained) parameters
    torch.testing.assert_close(rebuilt.dynamics.delta_low, trainer.model.dynamics.delta_low)
    assert float(rebuilt.dynamics.delta_high[0, 0]) == pytest.approx(0.5)
    other = CBMTrainer(layout, trainer.cfg, seed=1)
    other.load_state_dict(trainer.state_dict())
    assert other.updates == 3 and other.range_seen
    torch.testing.assert_close(other.model.reward_cmi(s, a, torch.zeros(32)), trainer.model.reward_cmi(s, a, torch.zeros(32)))
    with pytest.raises(ValueError, match="dynamics must be one of"):
        CBMConfig(dynamics="both")


def _projections_batch(g: torch.Generator, projection: torch.Tensor, b: int) -> tuple[torch.Tensor, ...]:
    """Chapter 4's controllable distractors alone: ``s'_k = P_k . a`` for a continuous action, ``s_k =
    P_k . a_prev`` (so the state holds redundant copies of the previous action), no reward."""
    prev, a = (torch.rand(b, projection.shape[1], generator=g) * 2 - 1 for _ in range(2))
    return prev @ projection.T, a, a @ projection.T


@pytest.mark.parametrize("target", ["delta", "next"])
def test_next_value_target_keeps_redundant_copies_of_the_previous_action_out_of_the_graph(target: str) -> None:
    """6 projections of a 3-D action: their change ``P_k a - s_k`` needs ``s_k``, which any 3 other
    factors also determine; a model of the change leans on those copies and the drop-one CMI counts
    them as edges. Eq. 4.1's label, the next value itself, needs the action alone."""
    k, d = 6, 3
    projection = torch.rand(k, d, generator=torch.Generator().manual_seed(2)) * 2 - 1
    projection /= projection.abs().sum(1, keepdim=True)
    layout = _layout(("continuous",) * k, (1,) * k, ("continuous", d))
    cfg = CBMConfig(target=target, num_negatives=64, eval_negatives=1024, lr=3e-3, batch_size=64)
    trainer, g = CBMTrainer(layout, cfg, seed=0), torch.Generator().manual_seed(0)
    for _ in range(600):
        trainer.update(*_projections_batch(g, projection, 64))
    cmi = trainer.model.dynamics_cmi(*_projections_batch(g, projection, 256), torch.Generator().manual_seed(1)).numpy()
    between = cmi[:, :k][~np.eye(k, dtype=bool)]
    assert cmi[:, k].min() > 0.3, cmi  # every factor reads the action
    if target == "next":
        assert between.max() < cfg.cmi_threshold, cmi
    else:
        assert between.max() >= cfg.cmi_threshold, cmi  # the spurious edges the option exists for


def test_auto_target_takes_next_values_for_overwritten_factors_and_changes_for_persistent_ones() -> None:
    """``target = "auto"``: a factor overwritten by the action (``c' = a``) varies less than its change and
    gets its next value as the label; a persistent one (``x' = x + 0.1 a``) gets its change; the choice
    travels with the weights and prediction adds the change back where it is one."""
    layout = _layout(("continuous", "continuous"), (1, 1), ("continuous", 1))
    g = torch.Generator().manual_seed(0)
    x, c, a = (torch.rand(64, 1, generator=g) * 2 - 1 for _ in range(3))
    state, nxt = torch.cat([x, c], 1), torch.cat([x + 0.1 * a, a], 1)
    cfg = CBMConfig(target="auto", feature_hidden=8, feature_dim=8, predictor_hidden=8, embed_dim=8)
    trainer = CBMTrainer(layout, cfg, seed=0)
    trainer.update(state, a, nxt)
    dynamics = trainer.model.dynamics
    assert dynamics.label_is_next.tolist() == [0.0, 1.0]
    labels = dynamics.label_deltas(state, nxt)
    torch.testing.assert_close(labels[0, :, 0], 0.1 * a[:, 0])
    torch.testing.assert_close(labels[1, :, 0], a[:, 0])
    trainer.update(state, a, -nxt)  # later batches widen the range but never change the choice
    assert dynamics.label_is_next.tolist() == [0.0, 1.0]
    rebuilt = model_from_config(json.loads(trainer.config_json()))
    import_tensors(rebuilt, export_tensors(trainer.model))
    assert rebuilt.dynamics.label_is_next.tolist() == [0.0, 1.0]
    predicted = rebuilt.dynamics.predict(state, a, num_candidates=64, generator=torch.Generator().manual_seed(1))
    low, high = rebuilt.dynamics.delta_low[:, 0], rebuilt.dynamics.delta_high[:, 0]
    assert bool(((predicted[:, 0] - x[:, 0] >= low[0] - 1e-6) & (predicted[:, 0] - x[:, 0] <= high[0] + 1e-6)).all())
    assert bool(((predicted[:, 1] >= low[1] - 1e-6) & (predicted[:, 1] <= high[1] + 1e-6)).all())
    names = dict(CBMTrainer(layout, CBMConfig(), seed=0).model.named_parameters())
    assert "dynamics.label_is_next" in dict(trainer.model.named_parameters())
    assert "dynamics.label_is_next" not in names  # delta and next: the weights of earlier runs still load
    with pytest.raises(ValueError, match="target must be one of"):
        CBMConfig(target="value")
    # the explicit variant (CDL's model) takes the same label; auto is the implicit model's alone
    assert [CBMConfig(dynamics="explicit", target=t).cdl().target for t in ("next", "delta", "auto")] == \
        ["next", "delta", "delta"]
