"""DCI (Eastwood and Williams 2018) as FLAM's Table 8.2 scores it: hand-built importance matrices and
hand-built codes, one factor per variable versus every factor mixing every variable."""
from __future__ import annotations

import pytest
import torch

from causal.dci import dci, entropy_score, position_dci, scores_from_importance

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


def _positions(m: int, n: int, grid: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Random cells ``[m, n, 2]`` and each agent's exact code: one-hot x and one-hot y ``[m, n, 2 grid]``."""
    generator = torch.Generator().manual_seed(seed)
    positions = torch.randint(grid, (m, n, 2), generator=generator)
    onehot = torch.nn.functional.one_hot(positions, grid).float().flatten(2)
    return positions, onehot


def test_factors_grouped_per_agent_each_encoding_one_agent_exactly_score_one() -> None:
    positions, code = _positions(800, 4, grid=6, seed=3)
    generator = torch.Generator().manual_seed(4)
    # factor k holds agent order[k]'s position; a fifth factor holds noise (a background slot)
    order = [2, 0, 3, 1]
    factors = torch.cat([code[:, order], torch.randn(800, 1, 12, generator=generator)], dim=1)
    scores = position_dci(factors + 0.05 * torch.randn(factors.shape, generator=generator), positions, grid_size=6)
    assert scores.importance.shape == (5, 4)
    assert scores.disentanglement > 0.9 and scores.completeness > 0.9 and scores.informativeness > 0.95
    assert scores.importance.argmax(0).tolist() == [1, 3, 0, 2]


def test_factors_mixing_every_agent_score_low_disentanglement() -> None:
    positions, code = _positions(800, 4, grid=6, seed=5)
    generator = torch.Generator().manual_seed(6)
    mixed = torch.einsum("mnc,kncd->mkd", code, torch.randn(4, 4, 12, 24, generator=generator))
    scores = position_dci(mixed + 0.05 * torch.randn(mixed.shape, generator=generator), positions, grid_size=6)
    assert scores.disentanglement < 0.4 and scores.completeness < 0.4
    assert scores.informativeness > 0.6


def test_random_codes_carry_no_position() -> None:
    positions, _ = _positions(800, 4, grid=8, seed=7)
    codes = torch.randn(800, 5, 16, generator=torch.Generator().manual_seed(8))
    scores = position_dci(codes, positions, grid_size=8)
    assert scores.informativeness < 0.25  # chance 1/8


def test_groups_sum_the_importance_of_their_variables() -> None:
    targets, codes = _variables(600, 4, seed=9)
    plain = dci(codes, targets, classes=5)
    grouped = dci(codes, targets, classes=5, groups=[0, 0, 1, 1])
    assert torch.allclose(grouped.importance, torch.stack([plain.importance[:, :2].sum(1),
                                                            plain.importance[:, 2:].sum(1)], 1), rtol=1e-5)
    assert grouped.informativeness == pytest.approx(plain.informativeness)
    # factors 0 and 1 both serve group 0: completeness halves, disentanglement stays high
    assert grouped.disentanglement > 0.9 and grouped.completeness < 0.6
    with pytest.raises(ValueError, match="one index"):
        dci(codes, targets, classes=5, groups=[0, 1])
