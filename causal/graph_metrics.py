"""Scoring a learned causal graph against the ground truth (ch. 3.3.3, Table 3.1).

The plain scores cover every entry of the ``d_S x (d_S + 1)`` graph except the diagonal: self-edges
are assumed (Assumption 4) and always kept, so counting them only inflates every metric.
The chapter selects the best threshold by a linear search on F1; we report the working threshold
and that best threshold side by side.

*With-self* scores (``with_self_*``, always computed) count every entry, self-edges included, with
each self-edge predicted present (CDL keeps them): the scoring of the chapter's Table 3.1, as far as
its numbers tell. Its manipulation column (recall 0.612, precision 0.980, accuracy 0.902) fixes the
share of true edges among the scored entries: errors = P (1 - r) + TP (1/p - 1) = 0.4005 P, so
P / N = 0.098 / 0.4005 = 0.2447. Our manipulation truth has 112 off-diagonal edges of 529 entries
(0.2117: those recall and precision would give accuracy 0.915) and 135 of 552 with the 23 self-edges
(0.2446). The plain scores stay the ones we optimise and compare runs by; ``with_self_*`` is the
figure to hold against the table.

*Identifiable* scores (:func:`score_graph` with ``constant_factors``) also leave out the columns of
factors that are constant in the environment by construction (the manipulation scene's ``z`` of
``unm``, ``rand`` and the markers): a cause that never varies carries no information, so no
learner can find its edges from the environment's data, and they cap recall whatever the learner.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np


REPORTED_SCORES = ("accuracy", "precision", "recall", "f1", "roc_auc", "best_threshold_f1",
                   "identifiable_accuracy", "identifiable_f1", "identifiable_best_threshold_f1",
                   "with_self_accuracy", "with_self_f1", "with_self_best_threshold_f1")
"""Scores of a global graph that every report carries where the env has a true graph (the
evaluator's gauges, ``causeway run --target-metric``)."""


def scored_entries(shape: tuple[int, int]) -> np.ndarray:
    """Boolean mask of the entries that are scored (all but the self-edges)."""
    mask = np.ones(shape, dtype=bool)
    n = shape[0]
    mask[np.arange(n), np.arange(n)] = False
    return mask


def identifiable_entries(shape: tuple[int, int], constant_factors: Sequence[int]) -> np.ndarray:
    """The scored entries whose cause can vary: all but the self-edges and the columns of
    ``constant_factors`` (factor indices; the action column is never constant)."""
    mask = scored_entries(shape)
    mask[:, list(constant_factors)] = False
    return mask


def self_edges_kept(cmi: np.ndarray) -> np.ndarray:
    """``cmi`` with every self-edge at +inf: present at any threshold, ranked above every other entry."""
    kept = np.array(cmi, dtype=np.float64)
    n = kept.shape[0]
    kept[np.arange(n), np.arange(n)] = np.inf
    return kept


def confusion(predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> dict[str, int]:
    """Counts over the entries of ``mask`` (default :func:`scored_entries`)."""
    mask = scored_entries(truth.shape) if mask is None else mask
    p, t = predicted.astype(bool)[mask], truth.astype(bool)[mask]
    return {"tp": int(np.sum(p & t)), "fp": int(np.sum(p & ~t)), "fn": int(np.sum(~p & t)), "tn": int(np.sum(~p & ~t))}


def binary_scores(predicted: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Accuracy, precision, recall and F1 of a 0/1 graph (precision is 0 when nothing is predicted)."""
    c = confusion(predicted, truth, mask)
    total = c["tp"] + c["fp"] + c["fn"] + c["tn"]
    precision = c["tp"] / (c["tp"] + c["fp"]) if c["tp"] + c["fp"] else 0.0
    recall = c["tp"] / (c["tp"] + c["fn"]) if c["tp"] + c["fn"] else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"accuracy": (c["tp"] + c["tn"]) / total, "precision": precision, "recall": recall, "f1": f1}


def roc_auc(scores: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Area under the ROC curve of edge scores (Mann-Whitney U with ties counted half)."""
    mask = scored_entries(truth.shape) if mask is None else mask
    s, t = scores[mask].astype(np.float64), truth[mask].astype(bool)
    pos, neg = s[t], s[~t]
    if len(pos) == 0 or len(neg) == 0:
        return 1.0
    order = np.argsort(np.concatenate([pos, neg]), kind="mergesort")
    ranks = np.empty(len(order))
    values = np.concatenate([pos, neg])[order]
    ranks[order] = _average_ranks(values)
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def average_precision(scores: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Area under the precision-recall curve as average precision: the sum over distinct thresholds
    (highest first) of precision there times the recall it adds (edge if score >= threshold; ties
    enter together, as in scikit-learn's ``average_precision_score``). 1.0 with no true edge."""
    mask = scored_entries(truth.shape) if mask is None else mask
    s, t = scores[mask].astype(np.float64), truth[mask].astype(bool)
    positives = int(t.sum())
    if positives == 0:
        return 1.0
    order = np.argsort(-s, kind="mergesort")
    s, t = s[order], t[order]
    last_of_tie = np.r_[s[1:] != s[:-1], True]
    tp = np.cumsum(t)[last_of_tie]
    seen = np.nonzero(last_of_tie)[0] + 1
    recall_gain = np.diff(np.r_[0, tp]) / positives
    return float(np.sum(recall_gain * tp / seen))


def score_local_graphs(scores: np.ndarray, truth: np.ndarray, threshold: float) -> dict[str, float]:
    """Local-graph scores (chapter 5's evaluation) of per-transition edge scores ``[B, d_S, d_S + 1]``
    against the true local graphs: ROC AUC, PR AUC (average precision) and the best F1 over every
    threshold, plus F1 / precision / recall at ``threshold``. Pooled over the off-diagonal entries of
    every transition (self-edges are always present and not scored), as the pooled variant of the
    chapter's evaluation code; ``positive_rate`` is the share of true edges among them."""
    mask = np.broadcast_to(scored_entries(truth.shape[1:]), truth.shape)
    best_t, best = best_threshold(scores, truth, mask=mask)
    at = binary_scores(scores >= threshold, truth, mask)
    return {"roc_auc": roc_auc(scores, truth, mask), "pr_auc": average_precision(scores, truth, mask),
            "best_f1": best["f1"], "best_threshold": best_t, "f1": at["f1"], "precision": at["precision"],
            "recall": at["recall"], "positive_rate": float(truth[mask].mean()) if mask.any() else 0.0}


def score_local_graphs_per_entry(scores: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """The other variant of the chapter's evaluation code: ROC AUC, PR AUC and best F1 of each
    off-diagonal entry ``(j, i)`` across the transitions, averaged over the entries whose true label
    varies (``entries`` of them). Each entry has its own best threshold, so scores need not be
    comparable between entries (as the pooled variant needs); ELDEN's partial derivatives are not
    (their scale differs by output head), pCMI's nats are closer to it."""
    per_entry = {"roc_auc": [], "pr_auc": [], "best_f1": []}
    everywhere = np.ones(truth.shape[0], dtype=bool)
    for j, i in zip(*np.nonzero(scored_entries(truth.shape[1:]))):
        labels = truth[:, j, i]
        if labels.min() == labels.max():
            continue
        column = scores[:, j, i]
        per_entry["roc_auc"].append(roc_auc(column, labels, everywhere))
        per_entry["pr_auc"].append(average_precision(column, labels, everywhere))
        per_entry["best_f1"].append(best_threshold(column, labels, mask=everywhere)[1]["f1"])
    means = {k: float(np.mean(v)) if v else float("nan") for k, v in per_entry.items()}
    return {**means, "entries": len(per_entry["roc_auc"])}


def _average_ranks(sorted_values: np.ndarray) -> np.ndarray:
    ranks = np.arange(1, len(sorted_values) + 1, dtype=np.float64)
    _, start, counts = np.unique(sorted_values, return_index=True, return_counts=True)
    for s, c in zip(start, counts):
        if c > 1:
            ranks[s : s + c] = ranks[s : s + c].mean()
    return ranks


def best_threshold(
    scores: np.ndarray, truth: np.ndarray, num: int | None = None, mask: np.ndarray | None = None
) -> tuple[float, dict[str, float]]:
    """The threshold with the best F1 over the scored entries, and the scores there.

    The chapter selects it by a linear search. By default (``num=None``) the search is exact: every
    distinct finite scored value is tried (edge if CMI >= it), which is what a linear search tends
    to as its step shrinks; ties go to the lowest threshold. ``num`` gives the older search instead,
    ``num`` evenly spaced thresholds from the smallest to the largest value. Its step is a
    two-hundredth of the CMI range, and the range is set by the strongest edges (nats on
    manipulation's action edges), so it is coarser than the gap between weak true edges and
    non-edges and gets coarser as those strong edges are learned. Entries at +inf (kept self-edges)
    count as present at every threshold.
    """
    mask = scored_entries(truth.shape) if mask is None else mask
    values, positive = scores[mask].astype(np.float64), truth[mask].astype(bool)
    finite = np.isfinite(values)
    if num is None:
        candidates = np.unique(values[finite])
        tp = _count_at_or_above(values[positive], candidates)
        fp = _count_at_or_above(values[~positive], candidates)
        f1 = 2 * tp / np.maximum(tp + fp + positive.sum(), 1)
        threshold = float(candidates[int(np.argmax(f1))])
        return threshold, binary_scores(scores >= threshold, truth, mask)
    lo, hi = float(np.min(values[finite])), float(np.max(values[finite]))
    best_t, best = lo, binary_scores(scores >= lo, truth, mask)
    for threshold in np.linspace(lo, hi, num)[1:]:
        result = binary_scores(scores >= threshold, truth, mask)
        if result["f1"] > best["f1"]:
            best_t, best = float(threshold), result
    return best_t, best


def _count_at_or_above(values: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """For each threshold, how many of ``values`` are >= it (+inf counts at every threshold)."""
    return len(values) - np.searchsorted(np.sort(values), thresholds, side="left")


def score_graph(
    cmi: np.ndarray, truth: np.ndarray, threshold: float, constant_factors: Sequence[int] | None = None,
    num: int | None = None, predicted: np.ndarray | None = None,
) -> dict[str, float]:
    """All the chapter's metrics: at the working threshold, ROC AUC, and at the best threshold.

    The same metrics over every entry, each self-edge kept, follow prefixed ``with_self_``
    (module docstring: the scoring Table 3.1's numbers imply). With ``constant_factors`` (factor
    indices, possibly none) the same metrics over
    :func:`identifiable_entries` follow, prefixed ``identifiable_`` (equal to the others when
    nothing is constant), with ``unidentifiable_true_edges``: the true edges left out. ``num`` selects
    the best-threshold search (:func:`best_threshold`: exact by default). ``predicted`` is the graph
    the working-point scores (accuracy, precision, recall, F1) judge when another rule than
    ``cmi >= threshold`` decided it (the FDR-tested graph, :mod:`causal.edge_tests`)."""
    predicted = cmi >= threshold if predicted is None else predicted.astype(bool)
    with_self = predicted | ~scored_entries(truth.shape)
    scores = _scores(cmi, truth, predicted, scored_entries(truth.shape), num)
    scores.update({f"with_self_{k}": v for k, v in
                   _scores(self_edges_kept(cmi), truth, with_self, np.ones(truth.shape, bool), num).items()})
    if constant_factors is not None:
        mask = identifiable_entries(truth.shape, constant_factors)
        scores.update({f"identifiable_{k}": v for k, v in _scores(cmi, truth, predicted, mask, num).items()})
        scores["unidentifiable_true_edges"] = float(np.sum(truth.astype(bool) & scored_entries(truth.shape) & ~mask))
    return scores


def _scores(cmi: np.ndarray, truth: np.ndarray, predicted: np.ndarray, mask: np.ndarray,
            num: int | None = None) -> dict[str, float]:
    scores = binary_scores(predicted, truth, mask)
    scores["roc_auc"] = roc_auc(cmi, truth, mask)
    t, best = best_threshold(cmi, truth, num, mask)
    scores["best_threshold"] = t
    scores.update({f"best_threshold_{k}": v for k, v in best.items()})
    return scores
