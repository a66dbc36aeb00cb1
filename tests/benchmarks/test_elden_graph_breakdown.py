"""The ELDEN local-graph breakdown: its Jacobian reductions against autograd, the normalisation by hand."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.elden_graph_breakdown import reductions, report, row_normalised
from causal.elden import ELDENConfig, ELDENModel
from causal.elden_graphs import member_local_graphs
from causal.factored import FactorLayout

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = ELDENConfig(members=2, token_hidden=8, embed_dim=8, heads=2, predictor_hidden=8, member_batch=4)
LAYOUT = FactorLayout(names=("a", "b"), kinds=("categorical",) * 2, sizes=(3, 2), locs=(0.0,) * 2,
                      scales=(1.0,) * 2, action_kind="categorical", action_size=2)


def test_reductions_of_the_jacobian_match_autograd_per_sample() -> None:
    torch.manual_seed(0)
    model = ELDENModel(LAYOUT, TINY)
    state = torch.tensor([[0, 1], [2, 0], [1, 1]], dtype=torch.float32)
    action, next_state = torch.tensor([[1.0], [0.0], [1.0]]), torch.tensor([[1, 1], [2, 1], [0, 0]], dtype=torch.float32)
    got = reductions(model, state, action, next_state, chunk=2)
    np.testing.assert_allclose(got["observed category (reference)"],
                               member_local_graphs(model, state, action, next_state).numpy(), rtol=1e-5, atol=1e-8)
    x = model.per_member(model.encode(state, action)).clone().requires_grad_(True)
    quantity = model.graph_quantity(model(x), model.targets(state, next_state))  # [M, B, d_S]
    valid = model.input_valid
    for j in range(2):
        (grad,) = torch.autograd.grad(quantity[..., j].sum(), x, retain_graph=True)  # [M, B, T, W]
        observed = (grad * x.detach()).sum(-1, keepdim=True)
        np.testing.assert_allclose(got["sum over categories"][:, :, j], (grad.abs() * valid).sum(-1).numpy(),
                                   rtol=1e-5, atol=1e-8)
        switch = ((grad - observed).abs() * valid).amax(-1)
        np.testing.assert_allclose(got["switch to another category"][:, :, j], switch.numpy(), rtol=1e-5, atol=1e-8)


def test_row_normalisation_divides_each_row_by_its_largest_off_diagonal_score() -> None:
    scores = np.array([[[5.0, 2.0, 4.0], [0.5, 9.0, 0.25]]])  # 2 factors + action; diagonal 5 and 9 ignored
    np.testing.assert_allclose(row_normalised(scores), [[[1.25, 0.5, 1.0], [1.0, 18.0, 0.5]]])


def test_report_names_the_most_frequent_false_positive() -> None:
    rng = np.random.default_rng(0)
    truth = np.zeros((20, 2, 3), dtype=np.uint8)
    truth[:10, 0, 1] = 1
    member = rng.random((2, 20, 2, 3)) * 0.1
    member[:, :10, 0, 1] += 1.0          # the true edge b -> a scores high when present
    member[:, :, 1, 2] += 2.0            # action -> b scores higher still, and is never an edge
    text = report({"observed category (reference)": member, "sum over categories": member,
                   "switch to another category": member}, truth, ["a", "b", "action"], top=1)
    assert "action -> b: 20" in text

