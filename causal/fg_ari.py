"""Foreground adjusted Rand index (FG-ARI): how well predicted object masks match the true ones.

The adjusted Rand index (Hubert and Arabie 1985) of two partitions of the same pixels, computed over
the pixels whose true label is not background (the object-centric literature's FG-ARI, Table 7.1's
metric). It is invariant to permutations of either labelling, 1 for identical partitions, about 0
for chance agreement, and may be negative. Where both partitions are trivial in the same way (one
cluster each, or every pixel its own cluster) the index is 0/0; it is then 1, as in scikit-learn.
"""
from __future__ import annotations

import numpy as np

BOUND_FG_ARI = 0.5
"""FG-ARI below which slots count as not bound to objects (the factor-extractor warns, ``summary.json``'s
``slots.bound`` is false): before binding, slot attention's held-out FG-ARI sits near 0, and once it
binds it passes 0.8 within a few hundred updates (docs/results.md, "How long the slots need")."""


def mean_fg_ari(true_labels: np.ndarray, pred_labels: np.ndarray) -> float | None:
    """Mean :func:`fg_ari` over the frames that have foreground (None if none has): frames without
    foreground have no FG-ARI."""
    per_frame = fg_ari(true_labels, pred_labels)
    finite = per_frame[np.isfinite(per_frame)]
    return float(finite.mean()) if len(finite) else None


def adjusted_rand_index(true: np.ndarray, pred: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """ARI per row of ``true`` and ``pred`` (int ``[B, P]``), over the pixels where ``weights`` (bool
    ``[B, P]``, default all) is set; vectorised over the batch through one contingency table per row."""
    true, pred = np.asarray(true, dtype=np.int64), np.asarray(pred, dtype=np.int64)
    if true.shape != pred.shape or true.ndim != 2:
        raise ValueError(f"true and pred must both be [B, P], got {true.shape} and {pred.shape}")
    weights = np.ones(true.shape, bool) if weights is None else np.asarray(weights, bool)
    rows = np.arange(len(true))[:, None]
    n_true, n_pred = true.max(initial=0) + 1, pred.max(initial=0) + 1
    table = np.zeros((len(true), n_true, n_pred))
    np.add.at(table, (np.broadcast_to(rows, true.shape), true, pred), weights.astype(float))
    pairs = _pairs(table).sum(axis=(1, 2))
    a, b = _pairs(table.sum(axis=2)).sum(axis=1), _pairs(table.sum(axis=1)).sum(axis=1)
    total = _pairs(table.sum(axis=(1, 2)))
    expected = np.divide(a * b, total, out=np.zeros_like(a), where=total > 0)
    best = 0.5 * (a + b)
    denominator = best - expected
    trivial = np.isclose(denominator, 0.0)
    return np.where(trivial, 1.0, (pairs - expected) / np.where(trivial, 1.0, denominator))


def fg_ari(true_labels: np.ndarray, pred_labels: np.ndarray, background: int = 0) -> np.ndarray:
    """FG-ARI per image of label maps ``[B, H, W]`` (or ``[B, P]``): ARI over the pixels whose true
    label is not ``background``. An image without foreground scores NaN."""
    true = np.asarray(true_labels).reshape(len(true_labels), -1)
    pred = np.asarray(pred_labels).reshape(len(pred_labels), -1)
    foreground = true != background
    scores = adjusted_rand_index(true, pred, foreground)
    return np.where(foreground.any(axis=1), scores, np.nan)


def _pairs(counts: np.ndarray) -> np.ndarray:
    return counts * (counts - 1.0) / 2.0
