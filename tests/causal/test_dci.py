"""DCI (Eastwood and Williams 2018) as FLAM's Table 8.2 scores it: hand-built importance matrices and
hand-built codes, one factor per variable versus every factor mixing every variable."""
from __future__ import annotations

import pytest
import torch

from causal.dci import dci, entropy_score, scores_from_importance

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_identity_importance_is_perfect_and_uniform_is_zero() -> None:
    perfect = scores_from_importance(torch.eye(4, dtype=torch.float64) * 3.0, [1.0, 0.5])
    assert perfect.disentanglement == pytest.approx(1.0) and perfect.completeness == pytest.approx(1.0)
    assert perfect.informativeness == pytest.approx(0.75)
    uniform = scores_from_importance(torch.ones(4, 4, dtype=torch.float64), [0.2])
    assert uniform.disentanglement == pytest.approx(0.0, abs=1e-9) and uniform.completeness == pytest.approx(0.0, abs=1e-9)


def test_two_factors_for_one_variable_halve_completeness_not_disentanglement() -> None:
    # variable 0 spread evenly over factors 0 and 1; variable 1 on factor 2 alone
    importance = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 2.0]], dtype=torch.float64)
    scores = scores_from_importance(importance, [1.0, 1.0])
    assert scores.disentanglement == pytest.approx(1.0)
    assert scores.completeness == pytest.approx((1 - 1 / torch.log2(torch.tensor(3.0)).item() + 1) / 2)
    assert entropy_score(torch.tensor([[0.5, 0.5]]), 2).item() == pytest.approx(0.0, abs=1e-9)


def _variables(m: int, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    targets = torch.randint(5, (m, n), generator=generator)
    embedding = torch.randn(5, 3, generator=generator)
    return targets, embedding[targets] + 0.05 * torch.randn(m, n, 3, generator=generator)


def test_one_factor_per_variable_scores_high() -> None:
    targets, codes = _variables(600, 4, seed=0)
    scores = dci(codes[:, [2, 0, 3, 1]], targets, classes=5)
    assert scores.disentanglement > 0.9 and scores.completeness > 0.9 and scores.informativeness > 0.9
    assert scores.importance.argmax(0).tolist() == [1, 3, 0, 2]


def test_every_factor_mixing_every_variable_scores_low() -> None:
    targets, codes = _variables(600, 4, seed=1)
    generator = torch.Generator().manual_seed(2)
    mixed = torch.einsum("mnc,knd->mkd", codes, torch.randn(4, 4, 3, generator=generator))
    scores = dci(mixed + 0.05 * torch.randn(mixed.shape, generator=generator), targets, classes=5)
    assert scores.disentanglement < 0.4 and scores.completeness < 0.4
    assert scores.informativeness > 0.6
