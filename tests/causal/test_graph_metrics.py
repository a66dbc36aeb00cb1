"""Graph scores against hand-computed values."""
from __future__ import annotations

import numpy as np

from causal.graph_metrics import best_threshold, binary_scores, confusion, roc_auc, score_graph

TRUTH = np.array([[1, 1, 0, 1],
                  [0, 1, 0, 1],
                  [0, 0, 1, 0]], dtype=np.uint8)  # 3 factors + action; 3 scored true edges of 9


def test_diagonal_is_not_scored() -> None:
    predicted = TRUTH.copy()
    np.fill_diagonal(predicted, 0)
    assert confusion(predicted, TRUTH) == {"tp": 3, "fp": 0, "fn": 0, "tn": 6}


def test_binary_scores_by_hand() -> None:
    predicted = np.array([[1, 1, 1, 0], [0, 1, 0, 1], [0, 0, 1, 0]])  # tp 2, fp 1, fn 1, tn 5
    s = binary_scores(predicted, TRUTH)
    assert s["accuracy"] == 7 / 9 and s["precision"] == 2 / 3 and s["recall"] == 2 / 3
    assert abs(s["f1"] - 2 / 3) < 1e-12
    empty = binary_scores(np.zeros_like(TRUTH), TRUTH)
    assert empty["precision"] == 0.0 and empty["recall"] == 0.0 and empty["f1"] == 0.0


def test_roc_auc_by_hand() -> None:
    scores = np.array([[9, 0.9, 0.1, 0.8], [0, 9, 0.3, 0.2], [0.25, 0.0, 9, 0.05]])
    # positives 0.9, 0.8, 0.2; negatives 0.1, 0.3, 0, 0.25, 0, 0.05 -> pairs won: 6 + 6 + 4 = 16 of 18
    assert abs(roc_auc(scores, TRUTH) - 16 / 18) < 1e-12
    tied = np.where(TRUTH > 0, 0.5, 0.5).astype(float)
    assert roc_auc(tied, TRUTH) == 0.5


def test_best_threshold_finds_perfect_separation() -> None:
    scores = np.where(TRUTH > 0, 0.05, 0.001)
    threshold, best = best_threshold(scores, TRUTH)
    assert best["f1"] == 1.0 and 0.001 < threshold <= 0.05
    s = score_graph(scores, TRUTH, threshold=0.1)
    assert s["f1"] == 0.0 and s["best_threshold_f1"] == 1.0 and s["roc_auc"] == 1.0
