"""DCI scores of a factored representation (Eastwood and Williams 2018), as FLAM's Table 8.2 uses them.

Each of ``K`` factors is a block of code dimensions; each of ``N`` ground-truth variables is
categorical. A linear probe (multinomial logistic regression, L1-penalised, on standardised codes)
predicts each variable from all codes, the chapter's "linear probe". The importance ``R[k, j]`` of
factor ``k`` for variable ``j`` is the absolute probe weight summed over factor ``k``'s dimensions
(DCI for multi-dimensional factors: D and C are over the ``K`` factors, never single dimensions) and
averaged over the classes (inputs are standardised, so weights are comparable). Where several
variables describe one ground-truth factor (an agent's ``x`` and ``y``), ``groups`` sums their
columns: ``R[k, g]`` is then factor ``k``'s importance for the group. Then, with ``P = R`` normalised:

    D = sum_k rho_k (1 - H_N(P[k, :])),   rho_k = sum_j R[k, j] / sum R   (disentanglement)
    C = mean_j (1 - H_K(P[:, j]))                                          (completeness)
    I = mean_j held-out accuracy of the probe for variable j               (informativeness)

with ``H_b`` the entropy in base ``b``. The L1 penalty plays the role of the original's lasso (it
zeroes the weights of factors that carry nothing about a variable); the chapter's probe is linear;
no scikit-learn here.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import torch
import torch.nn.functional as F


class DCI(NamedTuple):
    disentanglement: float
    completeness: float
    informativeness: float
    importance: torch.Tensor
    """``[K, N]``: factor ``k``'s importance for variable ``j``."""


def entropy_score(p: torch.Tensor, base: int) -> torch.Tensor:
    """``1 - H_base(p)`` along the last axis of rows ``p`` (non-negative, summing to one)."""
    if base < 2:
        return torch.ones(p.shape[:-1])
    h = -(p * torch.log(p.clamp_min(1e-12))).sum(-1) / math.log(base)
    return 1.0 - h


def fit_linear_probe(x: torch.Tensor, y: torch.Tensor, classes: int, l1: float = 0.01,
                     steps: int = 300, lr: float = 0.5) -> torch.nn.Linear:
    """L1-penalised multinomial logistic regression ``x [M, d] -> y [M]`` by proximal gradient
    descent (full batch; soft-thresholding after each step zeroes the weights of useless inputs)."""
    probe = torch.nn.Linear(x.shape[1], classes).to(x.dtype)
    torch.nn.init.zeros_(probe.weight)
    torch.nn.init.zeros_(probe.bias)  # a convex fit from a fixed start: the same probe on the same data
    for _ in range(steps):
        probe.zero_grad()
        F.cross_entropy(probe(x), y).backward()
        with torch.no_grad():
            for parameter in probe.parameters():
                parameter -= lr * parameter.grad
            probe.weight.copy_(probe.weight.sign() * (probe.weight.abs() - lr * l1).clamp_min(0.0))
    return probe


def dci(codes: torch.Tensor, targets: torch.Tensor, classes: int, train_fraction: float = 0.7,
        l1: float = 0.01, groups: Sequence[int] | None = None) -> DCI:
    """DCI of factor codes ``[M, K, d]`` against categorical variables ``targets`` int ``[M, N]``
    (values in ``[0, classes)``).

    The first ``train_fraction`` of the samples fit the probes (and the standardisation); the rest
    measure informativeness. ``groups`` (one group index per variable, ``0..G-1``) scores D and C
    against ``G`` ground-truth factors each described by its variables (importance summed over them);
    I stays the mean accuracy over all ``N`` probes."""
    m, k, d = codes.shape
    split = int(train_fraction * m)
    x = codes.reshape(m, k * d).double()
    x = (x - x[:split].mean(0)) / (x[:split].std(0) + 1e-8)
    importance, accuracy = torch.zeros(k, targets.shape[1], dtype=torch.float64), []
    with torch.enable_grad():
        for j in range(targets.shape[1]):
            probe = fit_linear_probe(x[:split], targets[:split, j].long(), classes, l1)
            with torch.no_grad():
                importance[:, j] = probe.weight.abs().view(classes, k, d).mean(dim=0).sum(dim=1)
                accuracy.append(float((probe(x[split:]).argmax(1) == targets[split:, j]).double().mean()))
    if groups is not None:
        index = torch.as_tensor(list(groups), dtype=torch.long)
        if len(index) != targets.shape[1] or index.min() < 0:
            raise ValueError(f"groups needs one index >= 0 per variable ({targets.shape[1]}), got {list(groups)}")
        importance = torch.zeros(k, int(index.max()) + 1, dtype=torch.float64).index_add_(1, index, importance)
    return scores_from_importance(importance, accuracy)


def position_dci(codes: torch.Tensor, positions: torch.Tensor, grid_size: int, train_fraction: float = 0.7) -> DCI:
    """Table 8.2's reading: how well each of ``K`` factors ``[M, K, d]`` encodes each agent's position
    ``[M, N, 2]`` (int cells ``0..grid_size-1``), by linear probes for every agent's ``x`` and ``y``
    (categorical), the two probes' importances summed per agent: D and C over factors and agents."""
    m, n = positions.shape[:2]
    targets = positions.reshape(m, 2 * n).long()
    return dci(codes, targets, classes=grid_size, train_fraction=train_fraction,
               groups=[i for i in range(n) for _ in range(2)])


def scores_from_importance(importance: torch.Tensor, accuracy: list[float]) -> DCI:
    """D and C of an importance matrix ``[K, N]``; I is the mean of the probes' accuracies."""
    total = importance.sum().clamp_min(1e-12)
    rho = importance.sum(1) / total
    per_factor = importance / importance.sum(1, keepdim=True).clamp_min(1e-12)
    per_variable = (importance / importance.sum(0, keepdim=True).clamp_min(1e-12)).T
    d = float((rho * entropy_score(per_factor, importance.shape[1])).sum())
    c = float(entropy_score(per_variable, importance.shape[0]).mean())
    return DCI(d, c, float(sum(accuracy) / len(accuracy)), importance.float())
