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

**The bias estimated from the data instead** (``bias="permuted"``, ``--evaluator-bias permuted``).
For every entry the learned model's CMI is also computed for the same input with its held-out values
permuted across the samples (the *null*: every dependence of the output on that input is broken,
its marginal kept), in the same pass. Per sample, the drop-one term is the same in both, so the
difference ``CMI - null`` is the full model's loss when input ``i`` is read from another sample:
``NLL(s'_j | s with s_i permuted, a) - NLL(s'_j | s, a)``, the permutation importance of ``i`` for
output ``j``. An entry is an edge when the one-sided test of ``CMI - null > 0`` rejects (its standard
error from those paired per-sample differences), Benjamini-Hochberg as above; ``min_cmi`` then only
says which non-edges are still undecided (their interval of ``CMI - null`` reaches it). Assumed:

* **Exchangeability.** For a non-edge (``s'_j`` independent of ``s_i`` given the other inputs) the
  permuted sample has the same distribution as the real one only if ``s_i`` is also independent of the
  other inputs; then ``E[CMI - null] = 0`` exactly, whatever the model's bias, and the test has its
  level. Transitions from episodes break it: in Chemical a colour spreads along the graph, so an
  object's colour depends on its ancestors' at the same step, permuting it makes inputs the model
  never saw, and where the model leans a little on a correlated non-parent (a proxy of its parent)
  the permutation costs likelihood while dropping it does not. The test then over-rejects; a
  conditional permutation would be needed, and we do not have one.

* **Samples independent across the permutation.** The paired differences of samples ``b`` and
  ``perm(b)`` share a value, so they are not quite independent; with thousands of samples and a
  random permutation the standard error from their spread is taken as is.
* The null is one permutation, drawn afresh per estimate (the evaluator's generator, seeded).

``bias="pooled"`` is the cautious variant: every entry of output ``j`` is tested against the largest
null of that output over its other inputs (with both standard errors), the bias of the input the
output uses least. It assumes the bias is mostly the output's (the drop-one model of output ``j`` is
trained less, whichever input is dropped) and that output ``j`` has at least one input it does not
use; a true edge's null is far below 0 (the full model leans on it), so edges do not set the level.
It gives up some power (the largest of several noisy nulls sits above the bias).

``bias="global"`` tests every entry against the largest null of the whole graph: a minimum effect
size estimated from the data, the largest CMI an input whose dependence was broken reaches in this
model. It sits where ``min_cmi`` sat and adapts to how well the model is trained (a less-trained
model's bias is larger, and so is its level), at the cost of the weak edges below it.

**The minimum effect size split from the CMI table itself** (``bias="split"``, ``--evaluator-bias
split``; no permuted null, so any method whose graph has standard errors can use it). The learned
model's bias falls as training goes on (docs/results.md), so a hand-set ``min_cmi`` fits one training
length. Here ``min_cmi`` is re-estimated from every estimate (:func:`split_level`): take the entries
whose CMI is significantly above 0 (Benjamini-Hochberg at ``fdr`` on ``CMI > 0``: the biased
non-edges and the edges), sort their log CMI, and find the largest gap between two neighbours that
both lie between the median of those entries and the method's fixed threshold ``cap`` (0.02 nats: an
entry above it is an edge under the chapter's rule anyway, so the rule only decides how far below it
to go), among the gaps with at least ``SPLIT_MIN_ABOVE`` (2) of those entries above them and below
``cap`` (one non-edge biased above the rest is not a cluster). The level is the geometric middle of
that gap, if the gap is at least ``SPLIT_MIN_RATIO`` (a factor of 2); then the test is ``CMI >
level`` as under ``fixed``. Assumed:

* **Two clusters in log CMI.** The non-edges' bias and the weak edges' CMI (at least two of them
  below ``cap``) are separated by a gap of at least a factor of 2, wider than any gap among the weak
  edges below ``cap``. Where there is
  no such gap there are no clusters and ``min_cmi`` is used (:func:`split_level` returns None). True
  edges whose CMI sits inside the bias cluster are given up, as under any ``min_cmi``, and so are
  weak edges below a wider gap among the edges; a non-edge biased above the gap is taken.
* **Sparsity**: at least half of the entries significantly above 0 are biased non-edges (in
  Chemical 2-5% of the tested entries are edges, and a model trained for thousands of updates has
  tens to a hundred non-edges significantly above 0), so the median lies in the bias cluster and the
  search starts there. A dense graph, or a model with almost no bias left, breaks it: the search
  then starts among the edges and the cut can fall between weak and strong edges.
* The level is only as good as the test that uses it: an edge just above the gap is found only if
  its CMI is significantly above the level (several standard errors, under Benjamini-Hochberg over
  hundreds of entries).

**The level from the negative side of the table** (``bias="mirror"``, ``--evaluator-bias mirror``; no
null, no number set by hand). A trained model's non-edges are estimated about as often below 0 as
above it, and as far out on either side (a drop-one model that fits as well as the full one: on
``random10`` after 4,000 updates, seeds 0 and 1, 466 and 476 of the ~880 non-edges are negative and
387 and 374 positive, the most negative -2.0e-3 and -1.1e-3 against the most positive 1.4e-3 and
1.7e-3), while an edge's CMI cannot be far below 0. So the negative side stands for the non-edges above a level ``t``: their expected number is
estimated as ``V(t) = #{CMI <= -t}``, and in the far tail, where that count is 0 or 1 and says
little, by a Pareto tail fitted to the largest ``MIRROR_TAIL`` (a tenth) of the negative magnitudes
(the Hill estimator: ``V(t) = k (t / u)^-alpha`` above their smallest, ``u``, with ``k`` of them).
The level is the smallest ``t`` among the entries' magnitudes with::

    V(t) <= fdr * max(#{CMI >= t}, 1)

(:func:`mirror_level`), the edges are the entries with ``CMI >= t``, and the level is capped at
``cap`` as ``split``'s is. With the bare count this is the knockoff filter's selection rule (Barber
and Candes, 2015) with each entry's CMI as its own statistic, whose sign is a fair coin for a
non-edge. Assumed, and what it gives:

* **Symmetry**: a non-edge's CMI estimate is as likely at ``-t`` as at ``+t``. A model whose
  non-edges are biased above 0 breaks it, and the rule then lets in more false edges than ``fdr``.
  Short-trained models are (docs/results.md); ``python -m benchmarks.fdr_graphs`` prints the rate
  reached on known graphs.
* **The tail**: beyond the largest negative the count says nothing, and with 5-10 edges (a
  5-object graph) one positive non-edge past it is a rate of 0.1-0.2 that the bare count accepts (0
  below ``-t`` is at most ``fdr`` of anything). The fitted tail still expects a fraction of a
  non-edge there, so the level goes past the largest non-edges unless enough edges lie beyond them.
  A power law is the cautious choice for a tail of unknown shape (heavier than an exponential). At
  least ``MIRROR_MIN_NEGATIVES`` negative entries are needed; with fewer, or where no ``t`` qualifies,
  :func:`mirror_level` returns None and ``min_cmi`` is tested as under ``fixed``.
* **What is controlled** is the rate on average over runs, not in each: with 20-30 edges one false
  edge is 0.03-0.05. The level is where the estimate allows it, so the rate reached is near the
  one requested rather than 0, unlike the tests against ``min_cmi``.
* No standard errors enter the level or the edges; an entry is undecided when its interval contains
  the level, so more held-out data still decides the entries next to it. Some non-edge's interval
  always reaches a level inside the non-edges' tail, so the stop rule lets such a run stop once the
  evaluator's draw is at its largest (``services.supervisor.stop_rules``).
* How it was chosen (read its figures as partly in-sample): the bare count was tried first on 3 runs
  of ``random10`` at 4,000 updates and 6 of collider and chain at 2,000; it let in 1-5 non-edges past
  the largest negative on 4 of them. The tail (a tenth, among a half, a fifth, a tenth and a
  twentieth) was chosen on the same 9 runs, then applied unchanged to the others (docs/results.md).

**The mirror of the permuted-input excess** (``bias="mirror-permuted"``, ``--evaluator-bias
mirror-permuted``; needs the permuted null). ``mirror`` fails where a model's non-edges are not
symmetric about 0: one trained long on a small graph leans a little on a few non-parents, their CMI
stays positive on held-out data and its positive tail reaches 3-5 times as far as the negative one
(``random:5:6:1`` after 65,000 updates: F1 0.76-0.88 against the oracle's 1.000). The permutation
importance ``CMI - null`` (above) removes what the model's use of a non-parent costs whatever value it
reads, so a non-edge's excess is centred on 0 again, and its z-score ``(CMI - null) / se`` more so
(an entry whose excess is large only because it is noisy scores low). The rule takes
:func:`mirror_level` of each, the excess's capped at ``cap`` and the z-score's uncapped
(:func:`mirror_permuted_levels`), and an entry is an edge when it reaches both. Assumed and found:

* **Symmetry of both statistics** for non-edges, as under ``mirror``; exchangeability of the
  permuted input (above) only on average over the non-edges, not per entry: a non-edge whose
  permuted input makes samples the model never saw gets a positive excess, and the z-score's level
  then has to be passed too.
* **Two selections, one rate.** Each level alone holds the rate on the non-edges its statistic
  orders; the edges are the entries both select, a subset of each. The rate reached is below the one
  requested (0.002 at 0.05, 0.016 at 0.1, 0.066 at 0.2 over 54 offline runs; docs/results.md).
* Where either level finds none (fewer than ``MIRROR_MIN_NEGATIVES`` negative entries), the test of
  ``CMI > min_cmi`` decides, as under ``mirror``; undecided entries are those whose interval of
  ``CMI - null`` reaches its level.
* How it was chosen (in-sample, then checked): five combinations (the excess alone, its z-score
  alone, the two together, the excess with Benjamini-Hochberg on its z-test, the excess with
  ``mirror``'s CMI level) were compared on the 30 offline runs ``mirror`` was measured on and the
  final models of 7 live runs; the two together were best (28 of 30, 7 of 7 within 0.03 F1 of the
  oracle) and were then run unchanged on 24 new runs (seeds 3-5): 23 of 24, ``mirror`` 18.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from proto.messages import BIASES, EDGE_RULES, NULL_BIASES

__all__ = ["BIASES", "EDGE_RULES", "MIRROR_MIN_NEGATIVES", "MIRROR_TAIL", "NULL_BIASES", "SPLIT_MIN_ABOVE", "SPLIT_MIN_RATIO", "EdgeEstimate", "benjamini_hochberg", "decide",
           "effect_level", "fdr_graph", "mirror_level", "mirror_permuted_levels", "p_values", "split_level", "tested_entries", "undecided"]

SPLIT_MIN_RATIO = 2.0
"""``bias="split"``: the smallest ratio of the CMIs either side of the cut that counts as two clusters."""
SPLIT_MIN_ABOVE = 2
"""``bias="split"``: the fewest entries between the cut and the cap that count as a cluster (one
non-edge biased above the rest is not one)."""
MIRROR_TAIL = 0.1
"""``bias="mirror"``: the share of the negative entries (the largest magnitudes) its Pareto tail is
fitted to."""
MIRROR_MIN_NEGATIVES = 20
"""``bias="mirror"``: the fewest negative entries it needs to stand for the non-edges."""


@dataclass(frozen=True)
class EdgeEstimate:
    """Per-entry CMI (mean of per-sample log-likelihood ratios), its standard error and sample count;
    with the permuted-input null (see the module's docstring) where it was computed: ``null`` is the
    CMI of the input permuted across samples, ``excess_stderr`` the standard error of ``cmi - null``."""

    cmi: np.ndarray
    stderr: np.ndarray
    samples: int
    null: np.ndarray | None = None
    excess_stderr: np.ndarray | None = None

    @classmethod
    def from_pointwise(cls, gains: np.ndarray, permuted: np.ndarray | None = None) -> "EdgeEstimate":
        """From per-sample ratios ``[B, d_S, d_S + 1]`` (nats) and, optionally, the per-sample losses of
        the full model when the entry's input is permuted (``CMI - null`` per sample, same shape)."""
        def mean_and_se(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            sd = x.std(axis=0, ddof=1) if x.shape[0] > 1 else np.zeros(x.shape[1:])
            return x.mean(axis=0), sd / math.sqrt(max(x.shape[0], 1))

        cmi, se = mean_and_se(gains)
        if permuted is None:
            return cls(cmi, se, gains.shape[0])
        excess, excess_se = mean_and_se(permuted)
        return cls(cmi, se, gains.shape[0], cmi - excess, excess_se)

    @classmethod
    def from_sums(cls, total: np.ndarray, squares: np.ndarray, n: int, permuted_total: np.ndarray | None = None,
                  permuted_squares: np.ndarray | None = None) -> "EdgeEstimate":
        """From the sums of the per-sample ratios and of their squares over ``n`` samples (a stream),
        and optionally the same sums of the per-sample ``CMI - null`` terms."""
        def mean_and_se(s: np.ndarray, sq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            mean = s / max(n, 1)
            var = np.clip(sq - n * mean**2, 0.0, None) / max(n - 1, 1)
            return mean, np.sqrt(var / max(n, 1)) if n > 1 else np.zeros_like(mean)

        cmi, se = mean_and_se(total, squares)
        if permuted_total is None or permuted_squares is None:
            return cls(cmi, se, n)
        excess, excess_se = mean_and_se(permuted_total, permuted_squares)
        return cls(cmi, se, n, cmi - excess, excess_se)

    def interval(self, z: float = 1.96) -> tuple[np.ndarray, np.ndarray]:
        """A two-sided normal confidence interval (95% by default)."""
        return self.cmi - z * self.stderr, self.cmi + z * self.stderr

    def excess(self, bias: str = "permuted") -> tuple[np.ndarray, np.ndarray]:
        """``cmi`` above the estimated bias and its standard error (ValueError without the null).

        ``permuted``: ``cmi - null`` per entry, from the paired per-sample differences. ``pooled``:
        ``cmi - max_i null[j, i]`` (over the inputs of output ``j`` but itself); ``global``: ``cmi -``
        the largest null of the whole graph (self-edges left out); with the standard errors of the
        two added in quadrature, the null's taken as ``stderr + excess_stderr`` at
        its arg-max (an upper bound on the standard error of ``cmi - (cmi - null)``, whatever
        the correlation of the two terms)."""
        if self.null is None or self.excess_stderr is None:
            raise ValueError("this estimate has no permuted-input null (estimate it with a generator)")
        if bias in ("permuted", "mirror-permuted"):
            return self.cmi - self.null, self.excess_stderr
        others = np.where(tested_entries(self.null.shape), self.null, -np.inf)
        if bias == "global":
            top = np.unravel_index(others.argmax(), others.shape)
            level, level_se = self.null[top], (self.stderr + self.excess_stderr)[top]
        else:
            index = others.argmax(axis=1)[:, None]
            level = np.take_along_axis(self.null, index, axis=1)
            level_se = np.take_along_axis(self.stderr + self.excess_stderr, index, axis=1)
        return self.cmi - level, np.sqrt(self.stderr**2 + level_se**2)


def _one_sided(excess: np.ndarray, stderr: np.ndarray) -> np.ndarray:
    safe = np.where(stderr > 0, stderr, 1.0)
    p = 0.5 * np.vectorize(math.erfc)(excess / safe / math.sqrt(2.0))
    return np.where(stderr > 0, p, np.where(excess > 0, 0.0, 1.0))


def p_values(estimate: EdgeEstimate, min_cmi: float, bias: str = "fixed") -> np.ndarray:
    """One-sided p-values per entry of ``CMI > min_cmi`` (``bias`` fixed or split: the caller passes
    :func:`effect_level`'s level) or of ``CMI > null`` (``"permuted"``, ``"pooled"``, ``"global"``);
    0 or 1 where the standard error is 0."""
    if bias not in BIASES:
        raise ValueError(f"bias must be one of {BIASES}, got {bias!r}")
    if bias in NULL_BIASES:
        return _one_sided(*estimate.excess(bias))
    return _one_sided(estimate.cmi - min_cmi, estimate.stderr)


def split_level(estimate: EdgeEstimate, fdr: float, cap: float = math.inf) -> float | None:
    """``bias="split"``'s minimum effect size (module docstring): the geometric middle of the largest
    gap in log CMI between the median of the entries significantly above 0 and ``cap`` that leaves
    ``SPLIT_MIN_ABOVE`` of them above it; None where there are no two clusters (fewer than 3 such
    entries, or no such gap of ``SPLIT_MIN_RATIO``)."""
    tested = tested_entries(estimate.cmi.shape)
    cmi = estimate.cmi[tested]
    positive = benjamini_hochberg(_one_sided(cmi, estimate.stderr[tested]), fdr) & (cmi > 0)
    x = np.sort(np.log(cmi[positive].astype(np.float64)))
    if x.size < 3:
        return None
    window = x[(x >= np.median(x)) & (x <= math.log(cap))]
    if window.size < 1 + SPLIT_MIN_ABOVE:
        return None
    gaps = np.diff(window)
    gaps[window.size - SPLIT_MIN_ABOVE:] = -np.inf   # a cut leaves at least SPLIT_MIN_ABOVE entries above it
    cut = int(np.argmax(gaps))
    if gaps[cut] < math.log(SPLIT_MIN_RATIO):
        return None
    return float(math.exp((window[cut] + window[cut + 1]) / 2))


def mirror_level(estimate: EdgeEstimate, fdr: float, cap: float = math.inf) -> float | None:
    """``bias="mirror"``'s level (module docstring): the smallest ``t`` among the tested entries' CMI
    magnitudes with ``V(t) <= fdr * max(#{CMI >= t}, 1)``, ``V`` the count of entries at or below
    ``-t`` and, past the smallest of the largest ``MIRROR_TAIL`` of the negative magnitudes, their
    fitted Pareto tail; at most ``cap``. None with fewer than ``MIRROR_MIN_NEGATIVES`` negative
    entries, or where no ``t`` qualifies."""
    x = np.asarray(estimate.cmi, dtype=np.float64)[tested_entries(estimate.cmi.shape)]
    negative = np.sort(-x[x < 0])
    if negative.size < MIRROR_MIN_NEGATIVES:
        return None
    tail = negative[-max(int(round(MIRROR_TAIL * negative.size)), 2):]
    u, exceed = tail[0], tail[1:]
    alpha = exceed.size / max(float(np.log(exceed / u).sum()), 1e-12)   # Hill's estimator of the tail index
    ordered = np.sort(x)
    t = np.unique(np.abs(x[x != 0]))
    above = ordered.size - np.searchsorted(ordered, t, side="left")
    below = np.searchsorted(ordered, -t, side="right").astype(np.float64)
    beyond = t > u
    below[beyond] = exceed.size * (t[beyond] / u) ** -alpha
    ok = np.nonzero(below <= fdr * np.maximum(above, 1))[0]
    if not ok.size:
        return None
    return float(min(t[ok[0]], cap))


def _excess_and_z(estimate: EdgeEstimate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``CMI - null``, its standard error and its z-score (0 where the standard error is 0)."""
    excess, stderr = estimate.excess("mirror-permuted")
    return excess, stderr, np.where(stderr > 0, excess / np.where(stderr > 0, stderr, 1.0), 0.0)


def mirror_permuted_levels(estimate: EdgeEstimate, fdr: float, cap: float = math.inf) -> tuple[float, float] | None:
    """``bias="mirror-permuted"``'s two levels (module docstring): :func:`mirror_level` of the
    permuted-input excess ``CMI - null`` (at most ``cap``) and of its z-score ``(CMI - null) / se``
    (uncapped); None where either finds none (or the estimate has no null)."""
    if estimate.null is None or estimate.excess_stderr is None:
        return None
    excess, stderr, z = _excess_and_z(estimate)
    level = mirror_level(EdgeEstimate(excess, stderr, estimate.samples), fdr, cap)
    z_level = mirror_level(EdgeEstimate(z, np.ones_like(z), estimate.samples), fdr)
    return None if level is None or z_level is None else (level, z_level)


def effect_level(estimate: EdgeEstimate, fdr: float, min_cmi: float, bias: str = "fixed",
                 cap: float = math.inf) -> float:
    """The minimum effect size the fdr rule tests against (under ``mirror``: the level an edge's CMI
    reaches; under ``mirror-permuted``: the level its ``CMI - null`` reaches): :func:`split_level`
    under ``bias="split"``, :func:`mirror_level` under ``"mirror"`` and the first of
    :func:`mirror_permuted_levels` under ``"mirror-permuted"`` (``min_cmi`` where they find none),
    ``min_cmi`` otherwise."""
    if bias == "mirror-permuted":
        levels = mirror_permuted_levels(estimate, fdr, cap)
        return min_cmi if levels is None else levels[0]
    level = {"split": split_level, "mirror": mirror_level}.get(bias)
    found = None if level is None else level(estimate, fdr, cap)
    return min_cmi if found is None else found


def tested_entries(shape: tuple[int, ...]) -> np.ndarray:
    """Which entries are tested: all but the self-edges of a dynamics graph ``[d_S, d_S + 1]``; every
    entry of a reward graph ``[d_S + 1]``."""
    if len(shape) == 1:
        return np.ones(shape, dtype=bool)
    return ~np.eye(*shape, dtype=bool)


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


def fdr_graph(estimate: EdgeEstimate, fdr: float, min_cmi: float, bias: str = "fixed",
              cap: float = math.inf) -> np.ndarray:
    """The edges (bool ``[d_S, d_S + 1]``) whose tests (:func:`p_values`) reject at ``fdr``; the
    self-edges are left out of the tests (kept by Assumption 4, added by the caller). A reward graph
    (``[d_S + 1]``) has no self-edges: every entry is tested. ``cap``: the split level's cap."""
    tested = tested_entries(estimate.cmi.shape)
    out = np.zeros(estimate.cmi.shape, dtype=bool)
    found = mirror_level(estimate, fdr, cap) if bias == "mirror" else None
    if found is not None:
        out[tested] = estimate.cmi[tested] >= found    # the level is the rate's own cut: no test above it
        return out
    if bias == "mirror-permuted":
        levels = mirror_permuted_levels(estimate, fdr, cap)
        if levels is None:   # too few negative entries to mirror: the test of CMI > min_cmi, as under mirror
            return fdr_graph(estimate, fdr, min_cmi, "fixed")
        excess, _, z = _excess_and_z(estimate)
        out[tested] = (excess[tested] >= levels[0]) & (z[tested] >= levels[1])
        return out
    level = effect_level(estimate, fdr, min_cmi, bias, cap)
    out[tested] = benjamini_hochberg(p_values(estimate, level, bias)[tested], fdr)
    return out


def undecided(estimate: EdgeEstimate, threshold: float, z: float = 1.96) -> np.ndarray:
    """Entries whose confidence interval contains ``threshold``: the data cannot yet say which side."""
    low, high = estimate.interval(z)
    return (low < threshold) & (high >= threshold)


def decide(estimate: EdgeEstimate, rule: str, threshold: float, fdr: float, min_cmi: float,
           z: float = 1.96, bias: str = "fixed") -> tuple[np.ndarray, np.ndarray]:
    """The edges and the undecided entries (bool ``[d_S, d_S + 1]``, self-edges neither) under ``rule``.

    ``fixed``: edge if ``cmi >= threshold``; undecided where the interval contains ``threshold``.
    ``fdr``: edge if the test rejects at ``fdr`` (:func:`fdr_graph`; ``bias`` says which test);
    undecided is an entry that is not an edge yet whose interval reaches ``min_cmi`` (of ``cmi``, or
    of ``cmi`` less the estimated bias under a null; under ``split`` the level it estimated, capped
    at ``threshold``): neither shown to be an edge nor shown to be below
    the smallest effect that counts. Either way more held-out data decides it."""
    if rule not in EDGE_RULES:
        raise ValueError(f"edge rule must be one of {EDGE_RULES}, got {rule!r}")
    off = tested_entries(estimate.cmi.shape)
    if rule == "fixed":
        return (estimate.cmi >= threshold) & off, undecided(estimate, threshold, z) & off
    edges = fdr_graph(estimate, fdr, min_cmi, bias, cap=threshold)
    excess, stderr = estimate.excess(bias) if bias in NULL_BIASES else (estimate.cmi, estimate.stderr)
    level = effect_level(estimate, fdr, min_cmi, bias, cap=threshold)
    return edges, ~edges & (excess + z * stderr >= level) & off
