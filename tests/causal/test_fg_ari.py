"""FG-ARI against hand-computed cases (each worked out in the comment beside it)."""
from __future__ import annotations

import numpy as np
import pytest

from causal.fg_ari import adjusted_rand_index, fg_ari


@pytest.mark.parametrize(("true", "pred", "expected"), [
    # identical up to a permutation of the predicted labels
    ([0, 0, 1, 1, 2], [2, 2, 0, 0, 1], 1.0),
    # pairs together in both: 1 (from {0,0}); a = C(2,2)+C(2,2) = 2, b = C(2,2) = 1, C(4,2) = 6;
    # expected = 2 * 1 / 6 = 1/3, max = (2 + 1) / 2 = 3/2 -> (1 - 1/3) / (3/2 - 1/3) = 4/7
    ([0, 0, 1, 1], [0, 0, 1, 2], 4.0 / 7.0),
    # no pair together in both: index 0; a = b = 2, expected = 4/6 = 2/3, max = 2 -> (0 - 2/3) / (4/3) = -1/2
    ([0, 0, 1, 1], [1, 0, 1, 0], -0.5),
    # contingency [[2, 1, 0], [0, 1, 2]]: index 1 + 1 = 2; a = 3 + 3 = 6, b = 1 + 1 + 1 = 3, C(6,2) = 15;
    # expected = 18/15 = 6/5, max = 9/2 -> (2 - 6/5) / (9/2 - 6/5) = (4/5) / (33/10) = 8/33
    ([0, 0, 0, 1, 1, 1], [0, 0, 1, 1, 2, 2], 8.0 / 33.0),
    # one true cluster split in two halves: index 2, a = 6, b = 2, expected = 2, max = 4 -> 0
    ([3, 3, 3, 3], [0, 0, 1, 1], 0.0),
    # both a single cluster: 0/0, defined as 1
    ([1, 1, 1], [4, 4, 4], 1.0),
])
def test_adjusted_rand_index_by_hand(true: list[int], pred: list[int], expected: float) -> None:
    score = adjusted_rand_index(np.array([true]), np.array([pred]))
    np.testing.assert_allclose(score, [expected], rtol=1e-12, atol=1e-12)


def test_fg_ari_ignores_background_pixels() -> None:
    true = np.array([[[0, 0, 1], [1, 2, 2]]])
    pred = np.array([[[1, 0, 3], [3, 0, 0]]])
    np.testing.assert_allclose(fg_ari(true, pred), [1.0])
    wrong_background = np.array([[[3, 3, 3], [3, 0, 0]]])
    np.testing.assert_allclose(fg_ari(true, wrong_background), [1.0])
    merged = np.array([[[0, 0, 1], [1, 1, 1]]])
    np.testing.assert_allclose(fg_ari(true, merged), [0.0])


def test_fg_ari_is_batched_row_by_row_and_nan_without_foreground() -> None:
    rng = np.random.default_rng(0)
    true, pred = rng.integers(0, 4, size=(5, 8, 8)), rng.integers(0, 3, size=(5, 8, 8))
    batched = fg_ari(true, pred)
    single = [fg_ari(true[i : i + 1], pred[i : i + 1])[0] for i in range(5)]
    np.testing.assert_allclose(batched, single, rtol=1e-12)
    assert np.all(np.abs(batched) < 0.2)
    assert np.isnan(fg_ari(np.zeros((1, 4, 4), int), pred[:1, :4, :4])[0])
