"""Edges a user can trust without a ground truth (issue 22): CMI with a standard error, and a graph
whose edges are decided by tests at a false-discovery rate the user sets.

The per-sample log-likelihood ratios behind a CMI estimate (``CDLModel.pointwise_cmi``: its mean
over samples is the CMI) give each entry a standard error directly, ``sd / sqrt(n)``. An entry is an
edge when the test of ``CMI > min_cmi`` rejects at the Benjamini-Hochberg level ``fdr`` over all
``d_S x (d_S + 1)`` entries (self-edges are kept and not tested).

What is assumed, and why:

* **A minimum effect size ``min_cmi``.** A learned masked model's CMI of a non-edge is not 0 but
  slightly positive: the drop-one model is trained less than the full one, so dropping any input
  costs a little likelihood. On Chemical ``full`` (10 objects, a 2,500-update model, 20k held-out
  transitions) non-edges reach 1.1e-3 nats and a tenth of them have z > 3, so testing ``CMI > 0``
  gives a false-discovery rate of 0.77 at a requested 0.05. Testing ``CMI > 5e-4`` gives 0.026
  there (F1 0.88 against 0.72 for the fixed 0.02-nat threshold and 0.90 for the oracle threshold).
  Less trained models are biased more: after 2,000 updates on 5-object graphs and 1,200 on
  ``random10`` the false discoveries at ``5e-4`` sat at 0.7e-3 to 2.2e-3 nats (standard errors
  0.6e-4 to 3.2e-4) and the false-discovery rate reached 0.18-0.39; ``2e-3`` left one at 3.1e-3
  (chain), ``5e-3``, the evaluator's default, none (docs/results.md). ``min_cmi`` is a stated
  assumption about the estimator's bias, a quarter of the chapter's 0.02; true edges weaker than it
  (the weakest we know of are ~3e-3 nats) are given up.
* **Normal test statistics.** The mean of thousands of per-sample ratios is close to normal; the
  p-value is one-sided, ``P(Z > (CMI - min_cmi) / se)``.
* **Dependence.** The tests share samples, so they are dependent; Benjamini-Hochberg keeps its level
  under positive regression dependence, which we assume and check on known graphs
  (``python -m benchmarks.fdr_graphs``) rather than prove.
* An entry whose per-sample ratios are all equal (its input is never the one the max aggregate
  uses) has standard error 0 and is decided by its mean alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from proto.messages import EDGE_RULES

__all__ = ["EDGE_RULES", "EdgeEstimate", "benjamini_hochberg", "decide", "fdr_graph", "p_values", "undecided"]


@dataclass(frozen=True)
class EdgeEstimate:
    """Per-entry CMI (mean of per-sample log-likelihood ratios), its standard error and sample count."""

    cmi: np.ndarray
    stderr: np.ndarray
    samples: int

    @classmethod
    def from_pointwise(cls, gains: np.ndarray) -> "EdgeEstimate":
        """From per-sample ratios ``[B, d_S, d_S + 1]`` (nats)."""
        n = gains.shape[0]
        sd = gains.std(axis=0, ddof=1) if n > 1 else np.zeros(gains.shape[1:])
        return cls(gains.mean(axis=0), sd / math.sqrt(max(n, 1)), n)

    @classmethod
    def from_sums(cls, total: np.ndarray, squares: np.ndarray, n: int) -> "EdgeEstimate":
        """From the sums of the per-sample ratios and of their squares over ``n`` samples (a stream)."""
        mean = total / max(n, 1)
        var = np.clip(squares - n * mean**2, 0.0, None) / max(n - 1, 1)
        return cls(mean, np.sqrt(var / max(n, 1)) if n > 1 else np.zeros_like(mean), n)

    def interval(self, z: float = 1.96) -> tuple[np.ndarray, np.ndarray]:
        """A two-sided normal confidence interval (95% by default)."""
        return self.cmi - z * self.stderr, self.cmi + z * self.stderr


def p_values(estimate: EdgeEstimate, min_cmi: float) -> np.ndarray:
    """One-sided p-values of ``CMI > min_cmi`` per entry (0 or 1 where the standard error is 0)."""
    excess = estimate.cmi - min_cmi
    safe = np.where(estimate.stderr > 0, estimate.stderr, 1.0)
    z = excess / safe
    p = 0.5 * np.vectorize(math.erfc)(z / math.sqrt(2.0))
    return np.where(estimate.stderr > 0, p, np.where(excess > 0, 0.0, 1.0))


def benjamini_hochberg(p: np.ndarray, fdr: float) -> np.ndarray:
    """Which of ``p`` are discoveries at false-discovery rate ``fdr`` (step-up procedure)."""
    flat = np.asarray(p, dtype=np.float64).ravel()
    m = flat.size
    order = np.argsort(flat, kind="mergesort")
    passed = np.nonzero(flat[order] <= fdr * np.arange(1, m + 1) / m)[0]
    out = np.zeros(m, dtype=bool)
    if passed.size:
        out[order[: passed[-1] + 1]] = True
    return out.reshape(np.shape(p))


def fdr_graph(estimate: EdgeEstimate, fdr: float, min_cmi: float) -> np.ndarray:
    """The edges (bool ``[d_S, d_S + 1]``) whose ``CMI > min_cmi`` tests reject at ``fdr``; the
    self-edges are left out of the tests (kept by Assumption 4, added by the caller)."""
    n = estimate.cmi.shape[0]
    tested = ~np.eye(n, n + 1, dtype=bool)
    out = np.zeros(estimate.cmi.shape, dtype=bool)
    out[tested] = benjamini_hochberg(p_values(estimate, min_cmi)[tested], fdr)
    return out


def undecided(estimate: EdgeEstimate, threshold: float, z: float = 1.96) -> np.ndarray:
    """Entries whose confidence interval contains ``threshold``: the data cannot yet say which side."""
    low, high = estimate.interval(z)
    return (low < threshold) & (high >= threshold)


def decide(estimate: EdgeEstimate, rule: str, threshold: float, fdr: float, min_cmi: float,
           z: float = 1.96) -> tuple[np.ndarray, np.ndarray]:
    """The edges and the undecided entries (bool ``[d_S, d_S + 1]``, self-edges neither) under ``rule``.

    ``fixed``: edge if ``cmi >= threshold``; undecided where the interval contains ``threshold``.
    ``fdr``: edge if the ``CMI > min_cmi`` test rejects at ``fdr`` (:func:`fdr_graph`); undecided is
    an entry that is not an edge yet whose interval reaches ``min_cmi`` (neither shown to be an edge
    nor shown to be below the smallest effect that counts). Either way more held-out data decides it."""
    if rule not in EDGE_RULES:
        raise ValueError(f"edge rule must be one of {EDGE_RULES}, got {rule!r}")
    off = ~np.eye(*estimate.cmi.shape, dtype=bool)
    if rule == "fixed":
        return (estimate.cmi >= threshold) & off, undecided(estimate, threshold, z) & off
    edges = fdr_graph(estimate, fdr, min_cmi)
    return edges, ~edges & (estimate.interval(z)[1] >= min_cmi) & off
