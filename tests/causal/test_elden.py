"""ELDEN (ch. 5): Jacobian local graphs against analytic and per-sample derivatives, the attention
baseline, Mixup, the gradient regulariser, the graph-variance reward, priorities and checkpoints."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from causal.elden import ELDENConfig, ELDENModel, Targets
from causal.elden_graphs import attention_graphs, edge_variance, graph_variance, jacobian_graphs, member_local_graphs
from causal.elden_trainer import ELDENTrainer, mixup
from causal.factored import FactorLayout

pytestmark = pytest.mark.usefixtures("one_torch_thread")


TINY = ELDENConfig(members=3, token_hidden=8, embed_dim=8, heads=2, predictor_hidden=8, member_batch=8)
CATEGORICAL = FactorLayout(names=("a", "b", "c"), kinds=("categorical",) * 3, sizes=(3, 2, 3), locs=(0.0,) * 3,
                           scales=(1.0,) * 3, action_kind="categorical", action_size=2)
MIXED = FactorLayout(names=("c", "x", "v"), kinds=("categorical", "continuous", "continuous"), sizes=(3, 1, 2),
                     locs=(0.0, 0.0, 0.0), scales=(1.0, 2.0, 1.0), action_kind="continuous", action_size=2)


def transitions(layout: FactorLayout, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)

    def state() -> np.ndarray:
        cols = [rng.integers(0, s, (n, 1)) if k == "categorical" else rng.normal(0, 1, (n, s))
                for k, s in zip(layout.kinds, layout.sizes)]
        return np.concatenate(cols, axis=1)
    action = (rng.integers(0, layout.action_size, (n, 1)) if layout.action_kind == "categorical"
              else rng.normal(0, 1, (n, layout.action_size)))
    return tuple(torch.tensor(a, dtype=torch.float32) for a in (state(), action, state()))


class LinearSoftmax(ELDENModel):
    """A hand-built ELDEN model: member m's logits of factor j are ``W[m, j] . x`` (x: every one-hot
    input, flattened), so ``d log p(y_j) / d x_{i,k} = W[m, j, (i,k), y] - sum_c p_c W[m, j, (i,k), c]``."""

    def __init__(self, weight: torch.Tensor) -> None:
        super().__init__(CATEGORICAL, TINY)
        self.weight = nn.Parameter(weight)

    def raw(self, params: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        return torch.einsum("mbi,mjio->mbjo", x.flatten(2), params["weight"])


def analytic_graphs(weight: np.ndarray, x: np.ndarray, labels: np.ndarray, model: ELDENModel) -> np.ndarray:
    m_, j_, _, _ = weight.shape
    b_, t_, w_ = x.shape
    out = np.zeros((m_, b_, j_, t_))
    valid = model.cat_class_mask.numpy()
    for m in range(m_):
        for b in range(b_):
            for j in range(j_):
                logits = x[b].reshape(-1) @ weight[m, j]
                logits = np.where(valid[j], logits, -np.inf)
                p = np.exp(logits - logits.max())
                p /= p.sum()
                for i in range(t_):
                    k = int(np.argmax(x[b, i]))
                    row = weight[m, j, i * w_ + k]
                    out[m, b, j, i] = abs(row[labels[b, j]] - (p * np.where(valid[j], row, 0)).sum())
    return out


def test_jacobian_local_graph_of_a_hand_built_model_equals_the_analytic_one() -> None:
    torch.manual_seed(0)
    model = LinearSoftmax(torch.zeros(3, 3, 4 * 3, 3))
    with torch.no_grad():  # factor a depends on b and the action; c on itself; b on nothing
        model.weight[:, 0, 3:6] = torch.randn(3, 3, 3)
        model.weight[:, 0, 9:11] = torch.randn(3, 2, 3)
        model.weight[:, 2, 6:9] = torch.randn(3, 3, 3)
    s, a, n = transitions(CATEGORICAL, 16)
    x, targets = model.encode(s, a), model.targets(s, n)
    got = member_local_graphs(model, s, a, n).numpy()
    labels = model.codec.categories(n).numpy()
    expected = analytic_graphs(model.weight.detach().numpy(), x.numpy(), labels, model)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert (got[:, :, 1] == 0).all() and (got[:, :, 0, [0, 2]] == 0).all() and (got[:, :, 2, :2] == 0).all()
    assert (got[:, :, 0, 1] > 0).all()
    assert jacobian_graphs(model, x, targets).shape == (3, 16, 3, 4)


@pytest.mark.parametrize("layout", [CATEGORICAL, MIXED])
def test_batched_jacobians_equal_per_sample_derivatives_of_the_attention_ensemble(layout: FactorLayout) -> None:
    torch.manual_seed(1)
    model = ELDENModel(layout, TINY)
    s, a, n = transitions(layout, 5, seed=2)
    got = member_local_graphs(model, s, a, n, chunk=2)
    x, targets = model.encode(s, a), model.targets(s, n)
    for b in range(5):
        one = x[b : b + 1].expand(3, 1, *x.shape[1:]).clone().requires_grad_(True)
        target = Targets(*(t[b : b + 1] for t in targets))
        quantity = model.graph_quantity(model(one), target)[:, 0]  # [M, d_S]
        for j in range(layout.num_factors):
            (grad,) = torch.autograd.grad(quantity[:, j].sum(), one, retain_graph=True)
            torch.testing.assert_close(got[:, b, j], model.reduce_inputs(grad[:, 0], one[:, 0].detach()),
                                       rtol=1e-4, atol=1e-7)


def test_continuous_inputs_sum_absolute_derivatives_over_their_valid_dimensions() -> None:
    model = ELDENModel(MIXED, TINY)
    jacobian = torch.ones(1, 4, model.width) * torch.tensor([1.0, -2.0, 3.0])
    x = torch.zeros(1, 4, model.width)
    x[0, 0, 1] = 1.0  # category 1 of factor c
    reduced = model.reduce_inputs(jacobian, x)[0]
    assert reduced.tolist() == [2.0, 1.0, 3.0, 3.0]  # c: d/dx at its category; x: 1 dim; v and action: 2 dims


def test_attention_baseline_is_a_distribution_over_inputs() -> None:
    model = ELDENModel(CATEGORICAL, TINY)
    s, a, _ = transitions(CATEGORICAL, 7)
    scores = attention_graphs(model, s, a)
    assert scores.shape == (7, 3, 4) and (scores >= 0).all()
    torch.testing.assert_close(scores.sum(-1), torch.ones(7, 3))  # attention rows compose to rows summing to 1


def test_mixup_mixes_inputs_and_labels_with_the_same_weights() -> None:
    x = torch.arange(12.0).view(1, 3, 2, 2)
    labels = torch.eye(3)[None, :, None, :].expand(1, 3, 1, 3)
    targets = Targets(labels, torch.zeros(1, 3, 0, 1), torch.zeros(1, 3, 0, 1))
    partner = torch.tensor([[1, 2, 0]])
    mixed, mixed_targets = mixup(x, targets, torch.tensor([[1.0, 0.5, 0.0]]), partner)
    torch.testing.assert_close(mixed[0, 0], x[0, 0])
    torch.testing.assert_close(mixed[0, 1], 0.5 * (x[0, 1] + x[0, 2]))
    torch.testing.assert_close(mixed[0, 2], x[0, 0])
    assert mixed_targets.labels[0, 1, 0].tolist() == [0.0, 0.5, 0.5]


def test_the_trainer_mixes_discrete_batches_with_u_shaped_weights_and_not_continuous_ones() -> None:
    trainer = ELDENTrainer(CATEGORICAL, TINY, seed=0)
    weights, partner = trainer._mixup_draw(3, 2000)
    extreme = ((weights < 0.05) | (weights > 0.95)).float().mean()
    assert 0.7 < extreme < 0.95 and abs(float(weights.mean()) - 0.5) < 0.05  # Beta(0.1, 0.1)
    assert sorted(partner[0].tolist()) == list(range(2000))
    assert trainer.uses_mixup and ELDENTrainer(MIXED, TINY, 0).uses_mixup  # a categorical factor
    assert not ELDENTrainer(CATEGORICAL, ELDENConfig(**{**TINY.__dict__, "mixup": False}), 0).uses_mixup
    continuous = FactorLayout(("x",), ("continuous",), (1,), (0.0,), (1.0,), "continuous", 1)
    assert not ELDENTrainer(continuous, TINY, 0).uses_mixup


def test_the_penalty_estimate_is_unbiased_for_the_sum_of_the_local_graph() -> None:
    torch.manual_seed(2)
    trainer = ELDENTrainer(CATEGORICAL, TINY, seed=3)
    s, a, n = transitions(CATEGORICAL, 24, seed=4)
    x, targets = trainer.split(s, a, n)
    with torch.no_grad():
        exact = float(jacobian_graphs(trainer.model, x, targets).sum(dim=(2, 3)).mean(dim=1).sum())
    x = x.requires_grad_(True)
    out = trainer.model(x)
    draws = [float(trainer.gradient_penalty(out, x, targets).detach()) for _ in range(300)]
    assert abs(np.mean(draws) - exact) < 0.05 * exact


def test_the_regulariser_shrinks_the_partial_derivatives() -> None:
    s, a, n = transitions(CATEGORICAL, 600, seed=5)
    penalties = {}
    for reg in (0.0, 1.0):
        trainer = ELDENTrainer(CATEGORICAL, ELDENConfig(**{**TINY.__dict__, "grad_reg": reg, "lr": 3e-3}), seed=0)
        for k in range(60):
            index = torch.arange(k * 24, k * 24 + 24) % 600
            trainer.update(s[index], a[index], n[index])
        penalties[reg] = float(member_local_graphs(trainer.model, s, a, n).sum(dim=(2, 3)).mean())
    assert penalties[1.0] < 0.5 * penalties[0.0], penalties


def test_the_reward_is_the_ensemble_variance_of_the_edges_by_hand() -> None:
    graphs = torch.zeros(4, 2, 2, 3)  # members, transitions, outputs, inputs
    graphs[:2, 0, 0, 1] = 1.0          # two of four members see edge 1 -> 0 in transition 0: variance 0.25
    graphs[:1, 0, 1, 2] = 1.0          # one of four sees 2 -> 1: variance 3/16
    graphs[:, 1] = 1.0                 # everyone agrees everywhere in transition 1
    agree = torch.tensor([[False, False], [False, False]])
    expected = torch.tensor([(0.25 + 3 / 16) / 6, 0.0])
    torch.testing.assert_close(edge_variance(graphs, 0.5, agree), expected)
    agree[0, 1] = True                 # members predict the same next value of factor 1: its row is 0
    torch.testing.assert_close(edge_variance(graphs, 0.5, agree), torch.tensor([0.25 / 6, 0.0]))


def test_graph_variance_of_a_hand_built_ensemble() -> None:
    torch.manual_seed(6)
    weight = torch.zeros(3, 3, 12, 3)
    weight[0, 0, 3:6] = 5 * torch.randn(3, 3)  # only member 0 reads b for factor a
    weight[:, 2, :3, 0] = 4.0                  # every member: c is predicted from a, class 0
    model = LinearSoftmax(weight)
    s, a, n = transitions(CATEGORICAL, 10, seed=7)
    members = member_local_graphs(model, s, a, n).numpy()
    variance = (members >= model.cfg.edge_threshold).var(axis=0)
    logits = np.einsum("bi,mjio->mbjo", model.encode(s, a).flatten(1).numpy(), weight.numpy())
    logits[..., 1, 2] = -np.inf  # factor b has two classes
    classes = logits.argmax(-1)
    variance[(classes == classes[:1]).all(axis=0)] = 0.0
    assert not (classes == classes[:1]).all(axis=0)[:, 0].all()  # members disagree on a somewhere
    np.testing.assert_allclose(graph_variance(model, s, a, n).numpy(), variance.mean(axis=(1, 2)), atol=1e-7)
    assert (graph_variance(model, s, a, n) > 0).any()


def test_priorities_follow_the_prediction_error_of_each_members_rows() -> None:
    trainer = ELDENTrainer(CATEGORICAL, ELDENConfig(**{**TINY.__dict__, "prioritised": True}), seed=0)
    s, a, n = transitions(CATEGORICAL, trainer.batch_size)
    x, targets = trainer.split(s, a, n)
    error = trainer.model.prediction_error(trainer.model(x), targets).sum(-1).detach()
    trainer.update(s, a, n)
    expected = (1 - torch.exp(-error)).sqrt().flatten().numpy()
    np.testing.assert_allclose(trainer.last_priorities, expected, rtol=1e-5)
    assert ELDENTrainer(CATEGORICAL, TINY, 0).last_priorities is None


def test_checkpoint_round_trip_continues_identically() -> None:
    s, a, n = transitions(MIXED, 48, seed=8)
    cfg = ELDENConfig(**{**TINY.__dict__, "member_batch": 16, "grad_reg": 1e-2})
    first = ELDENTrainer(MIXED, cfg, seed=1)
    first.update(s, a, n)
    second = ELDENTrainer(MIXED, cfg, seed=9)
    second.load_state_dict(first.state_dict())
    first.update(s, a, n)
    second.update(s, a, n)
    for p, q in zip(first.model.parameters(), second.model.parameters()):
        torch.testing.assert_close(p, q)


def test_prediction_nll_is_the_members_mean_nll() -> None:
    model = ELDENModel(MIXED, TINY)
    s, a, n = transitions(MIXED, 6)
    out = model(model.encode(s, a))
    expected = -model.log_likelihood(out, model.targets(s, n)).sum(-1).mean(0)
    torch.testing.assert_close(model.prediction_nll(s, a, n), expected.detach())


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="multiple of heads"):
        ELDENConfig(embed_dim=10, heads=4)
    with pytest.raises(ValueError, match="graph_of"):
        ELDENConfig(graph_of="nope")
    assert ELDENConfig().batch_size == 5 * 32
