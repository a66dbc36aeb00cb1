"""Scoring a learned causal graph against the ground truth (ch. 3.3.3, Table 3.1).

Scores cover every entry of the ``d_S x (d_S + 1)`` graph except the diagonal: self-edges are
assumed (Assumption 4) and always kept, so counting them would only inflate every metric.
The chapter selects the best threshold by a linear search on F1; we report the working threshold
and that best threshold side by side.
"""
from __future__ import annotations

import numpy as np


def scored_entries(shape: tuple[int, int]) -> np.ndarray:
    """Boolean mask of the entries that are scored (all but the self-edges)."""
    mask = np.ones(shape, dtype=bool)
    n = shape[0]
    mask[np.arange(n), np.arange(n)] = False
    return mask


def confusion(predicted: np.ndarray, truth: np.ndarray) -> dict[str, int]:
    mask = scored_entries(truth.shape)
    p, t = predicted.astype(bool)[mask], truth.astype(bool)[mask]
    return {"tp": int(np.sum(p & t)), "fp": int(np.sum(p & ~t)), "fn": int(np.sum(~p & t)), "tn": int(np.sum(~p & ~t))}


def binary_scores(predicted: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Accuracy, precision, recall and F1 of a 0/1 graph (precision is 0 when nothing is predicted)."""
    c = confusion(predicted, truth)
    total = c["tp"] + c["fp"] + c["fn"] + c["tn"]
    precision = c["tp"] / (c["tp"] + c["fp"]) if c["tp"] + c["fp"] else 0.0
    recall = c["tp"] / (c["tp"] + c["fn"]) if c["tp"] + c["fn"] else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"accuracy": (c["tp"] + c["tn"]) / total, "precision": precision, "recall": recall, "f1": f1}


def roc_auc(scores: np.ndarray, truth: np.ndarray) -> float:
    """Area under the ROC curve of edge scores (Mann-Whitney U with ties counted half)."""
    mask = scored_entries(truth.shape)
    s, t = scores[mask].astype(np.float64), truth[mask].astype(bool)
    pos, neg = s[t], s[~t]
    if len(pos) == 0 or len(neg) == 0:
        return 1.0
    order = np.argsort(np.concatenate([pos, neg]), kind="mergesort")
    ranks = np.empty(len(order))
    values = np.concatenate([pos, neg])[order]
    ranks[order] = _average_ranks(values)
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def _average_ranks(sorted_values: np.ndarray) -> np.ndarray:
    ranks = np.arange(1, len(sorted_values) + 1, dtype=np.float64)
    _, start, counts = np.unique(sorted_values, return_index=True, return_counts=True)
    for s, c in zip(start, counts):
        if c > 1:
            ranks[s : s + c] = ranks[s : s + c].mean()
    return ranks


def best_threshold(scores: np.ndarray, truth: np.ndarray, num: int = 200) -> tuple[float, dict[str, float]]:
    """Linear search over thresholds spanning the scored CMI values; returns (threshold, scores) at best F1."""
    mask = scored_entries(truth.shape)
    values = scores[mask]
    lo, hi = float(np.min(values)), float(np.max(values))
    best_t, best = lo, binary_scores(scores >= lo, truth)
    for threshold in np.linspace(lo, hi, num)[1:]:
        result = binary_scores(scores >= threshold, truth)
        if result["f1"] > best["f1"]:
            best_t, best = float(threshold), result
    return best_t, best


def score_graph(cmi: np.ndarray, truth: np.ndarray, threshold: float) -> dict[str, float]:
    """All the chapter's metrics: at the working threshold, ROC AUC, and at the best threshold."""
    scores = binary_scores(cmi >= threshold, truth)
    scores["roc_auc"] = roc_auc(cmi, truth)
    t, best = best_threshold(cmi, truth)
    scores["best_threshold"] = t
    scores.update({f"best_threshold_{k}": v for k, v in best.items()})
    return scores
