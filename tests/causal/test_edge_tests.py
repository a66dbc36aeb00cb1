"""CMI with a standard error and the FDR-tested graph (issue 22)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.edge_tests import (EdgeEstimate, benjamini_hochberg, decide, effect_level, fdr_graph, mirror_level,
                                mirror_permuted_levels, p_values,
                                split_level, undecided)


def test_benjamini_hochberg_by_hand() -> None:
    p = np.array([0.001, 0.008, 0.039, 0.041, 0.042, 0.06, 0.074, 0.205, 0.212, 0.216])
    # BH at 0.05 over 10: thresholds 0.005, 0.010, 0.015, 0.020, ...: the 2nd is the last below its own
    assert benjamini_hochberg(p, 0.05).tolist() == [True, True] + [False] * 8
    assert benjamini_hochberg(p, 0.2).sum() == 7  # thresholds 0.02 k: the 7th (0.074 <= 0.14) is the last below
    assert not benjamini_hochberg(np.ones(5), 0.05).any()


def test_standard_errors_and_p_values_from_per_sample_ratios() -> None:
    rng = np.random.default_rng(0)
    gains = rng.normal(0.01, 0.1, (10_000, 2, 3))
    gains[:, 0, 1] = 0.0  # an input never used: every ratio 0
    est = EdgeEstimate.from_pointwise(gains)
    assert abs(est.stderr[1, 2] - 0.1 / 100) < 1e-4 and est.stderr[0, 1] == 0.0
    p = p_values(est, min_cmi=0.0)
    assert p[0, 1] == 1.0 and p[1, 2] < 1e-10
    low, high = est.interval()
    assert (low <= est.cmi).all() and (est.cmi <= high).all()
    assert undecided(est, 0.01)[1, 2] and not undecided(est, 0.5)[1, 2]


def test_the_fdr_graph_keeps_its_false_discovery_rate_on_simulated_estimates() -> None:
    """Independent normal estimates, 10% true edges at small effects: the measured FDR over many
    repetitions stays near or below the requested level, and the self-edges are never tested."""
    rng = np.random.default_rng(1)
    fdp, power = [], []
    for _ in range(200):
        truth = rng.random((10, 11)) < 0.1
        cmi = np.where(truth, rng.uniform(0.002, 0.02, truth.shape), 0.0) + rng.normal(0, 0.001, truth.shape)
        est = EdgeEstimate(cmi, np.full(truth.shape, 0.001), 10_000)
        graph = fdr_graph(est, 0.1, 0.0)
        assert not graph[np.arange(10), np.arange(10)].any()
        off = ~np.eye(10, 11, dtype=bool)
        found = graph & off
        fdp.append((found & ~truth).sum() / max(found.sum(), 1))
        power.append((found & truth).sum() / max((truth & off).sum(), 1))
    assert np.mean(fdp) <= 0.1 * 1.25 and np.mean(power) > 0.6


def test_streamed_sums_give_the_same_estimate() -> None:
    gains = np.random.default_rng(2).normal(0.02, 0.3, (5_000, 3, 4))
    whole = EdgeEstimate.from_pointwise(gains)
    parts = [gains[:1_234], gains[1_234:]]
    streamed = EdgeEstimate.from_sums(sum(p.sum(0) for p in parts), sum((p**2).sum(0) for p in parts), 5_000)
    np.testing.assert_allclose(streamed.cmi, whole.cmi, rtol=1e-10)
    np.testing.assert_allclose(streamed.stderr, whole.stderr, rtol=1e-8)
    assert EdgeEstimate.from_sums(np.ones((1, 2)), np.ones((1, 2)), 1).stderr.tolist() == [[0.0, 0.0]]


def test_decide_under_each_rule_leaves_the_self_edges_out() -> None:
    cmi = np.array([[0.9, 0.021, 0.004, 0.0001], [0.05, 0.9, 0.0001, 0.003], [0.0001, 0.0001, 0.9, 0.03]])
    stderr = np.array([[0.01, 0.005, 0.0005, 0.0001], [0.001, 0.01, 0.0001, 0.004], [0.0001, 0.0001, 0.01, 0.001]])
    est = EdgeEstimate(cmi, stderr, 1_000)
    edges, open_ = decide(est, "fixed", 0.02, 0.05, 5e-4)
    assert np.argwhere(edges).tolist() == [[0, 1], [1, 0], [2, 3]]  # the diagonal is the caller's
    assert np.argwhere(open_).tolist() == [[0, 1]]  # 0.021 +- 0.0098 straddles 0.02
    edges, open_ = decide(est, "fdr", 0.02, 0.05, 5e-4)
    assert np.argwhere(edges).tolist() == [[0, 1], [0, 2], [1, 0], [2, 3]]  # 0.004 +- 0.0005 is an edge now
    assert np.argwhere(open_).tolist() == [[1, 3]]  # 0.003 +- 0.004: neither an edge nor below min_cmi
    with pytest.raises(ValueError, match="edge rule"):
        decide(est, "oracle", 0.02, 0.05, 5e-4)


def biased_model_terms(rng: np.random.Generator, n: int = 2_000, outputs: int = 6,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-sample terms of a learned model with a known truth (~15% edges) and a positive bias on
    every entry. Input x_i and output y_j are standard normal, y_j = rho x_i + noise on an edge; the
    full model's NLL uses x_i through ``-w x_i y_j`` (on a non-edge that is overfitting, mean 0), and
    dropping an input costs ``bias + noise`` (the drop-one model is trained less). So the CMI term is
    ``bias + w x y + noise`` and the permuted term (``CMI - null``) ``w (x - x_perm) y``."""
    inputs = outputs + 1
    truth = rng.random((outputs, inputs)) < 0.15
    rho = np.where(truth, rng.uniform(0.05, 0.3, truth.shape), 0.0)
    w = np.where(truth, 0.05, rng.uniform(0.0, 0.01, truth.shape))
    bias = rng.uniform(0.7e-3, 3e-3, truth.shape)
    x = rng.normal(size=(n, 1, inputs))
    y = rho * x + np.sqrt(1 - rho**2) * rng.normal(size=(n, outputs, inputs))
    x_perm = x[rng.permutation(n)]
    gains = bias + w * x * y + rng.normal(0, 0.01, (n, outputs, inputs))
    return gains, w * (x - x_perm) * y, truth


def test_the_estimated_bias_keeps_the_false_discovery_rate_where_min_cmi_0_does_not() -> None:
    """Synthetic per-sample ratios with a known bias on non-edges: over many seeded draws the FDR
    reached by the permuted-null test is near the requested one (0.073 at 0.1; it finds 88% of the
    edges), the pooled null's below it (0; 74%), while testing ``CMI > 0`` on the same draws is far
    above it (0.85: every non-edge is biased up)."""
    rng = np.random.default_rng(7)
    reached = {"permuted": [], "fixed": [], "pooled": [], "global": []}
    power = {bias: [] for bias in reached}
    for _ in range(200):
        gains, permuted, truth = biased_model_terms(rng)
        est = EdgeEstimate.from_pointwise(gains, permuted)
        off = ~np.eye(*truth.shape, dtype=bool)
        for bias in reached:
            found = fdr_graph(est, 0.1, 0.0, bias) & off
            reached[bias].append((found & ~truth).sum() / max(found.sum(), 1))
            power[bias].append((found & truth).sum() / max((truth & off).sum(), 1))
    assert np.mean(reached["permuted"]) <= 0.1 * 1.3, np.mean(reached["permuted"])
    assert np.mean(reached["fixed"]) > 0.5 and np.mean(power["permuted"]) > 0.6
    # pooled: every output's largest null is above each entry's own bias here, so it is conservative
    assert np.mean(reached["pooled"]) <= 0.1 and np.mean(power["pooled"]) > 0.5
    assert np.mean(reached["global"]) <= 0.1 and np.mean(power["global"]) > 0.4


def test_the_permuted_null_is_the_mean_of_cmi_minus_the_permuted_terms() -> None:
    rng = np.random.default_rng(8)
    gains, permuted, _ = biased_model_terms(rng, n=3_000)
    est = EdgeEstimate.from_pointwise(gains, permuted)
    np.testing.assert_allclose(est.null, (gains - permuted).mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(est.excess_stderr, permuted.std(axis=0, ddof=1) / np.sqrt(3_000), rtol=1e-10)
    parts = [(gains[:1_000], permuted[:1_000]), (gains[1_000:], permuted[1_000:])]
    streamed = EdgeEstimate.from_sums(sum(g.sum(0) for g, _ in parts), sum((g**2).sum(0) for g, _ in parts), 3_000,
                                      sum(p.sum(0) for _, p in parts), sum((p**2).sum(0) for _, p in parts))
    np.testing.assert_allclose(streamed.null, est.null, atol=1e-12)
    np.testing.assert_allclose(streamed.excess_stderr, est.excess_stderr, rtol=1e-8)
    with pytest.raises(ValueError, match="permuted-input null"):
        p_values(EdgeEstimate.from_pointwise(gains), 0.0, "permuted")
    with pytest.raises(ValueError, match="bias must be"):
        p_values(est, 0.0, "guessed")
    # pooled: each output's largest null over its other inputs, the standard errors in quadrature
    excess, se = est.excess("pooled")
    for j in range(est.cmi.shape[0]):
        i = max((i for i in range(est.cmi.shape[1]) if i != j), key=lambda i: est.null[j, i])
        np.testing.assert_allclose(excess[j], est.cmi[j] - est.null[j, i])
        np.testing.assert_allclose(se[j], np.hypot(est.stderr[j], est.stderr[j, i] + est.excess_stderr[j, i]))
    # global: the largest null of the whole graph, self-edges left out
    excess, se = est.excess("global")
    off = ~np.eye(*est.null.shape, dtype=bool)
    j, i = np.argwhere(off & (est.null == est.null[off].max()))[0]
    np.testing.assert_allclose(excess, est.cmi - est.null[j, i])
    np.testing.assert_allclose(se, np.hypot(est.stderr, est.stderr[j, i] + est.excess_stderr[j, i]))


def test_decide_with_the_permuted_null_marks_undecided_by_the_excess() -> None:
    cmi = np.array([[0.9, 0.004, 0.003], [0.002, 0.9, 0.0025]])
    null = np.array([[0.0, -0.001, 0.0029], [0.0021, 0.0, 0.0]])
    excess_se = np.array([[0.01, 0.0005, 0.0001], [0.003, 0.01, 0.0001]])
    est = EdgeEstimate(cmi, np.full(cmi.shape, 1e-4), 1_000, null, excess_se)
    edges, open_ = decide(est, "fdr", 0.02, 0.05, 5e-3, bias="permuted")
    # (0, 1): excess 0.005 +- 0.0005, an edge; (1, 2): 0.0025 +- 0.0001, an edge though below the
    # fixed 5e-3; (0, 2): excess 1e-4, not one; (1, 0): -1e-4 +- 3e-3, reaches 5e-3: undecided
    assert np.argwhere(edges).tolist() == [[0, 1], [1, 2]]
    assert np.argwhere(open_).tolist() == [[1, 0]]
    assert np.argwhere(decide(est, "fdr", 0.02, 0.05, 5e-3)[0]).tolist() == []  # fixed: all below 5e-3 + se


def test_a_small_trained_model_with_the_permuted_null_finds_its_graph() -> None:
    """CDL trained briefly on test_cdl's toy dynamics (independent inputs, so the null is exact):
    the permuted-null test at 0.05 gives the true graph, and the excess of the non-edges is centred
    on 0 (within a few standard errors). (At 250 updates the non-edges' CMI itself is off by up to
    0.03 nats either way, and testing CMI > 0 gave 4 false edges here.)"""
    from causal.cdl import CDLConfig
    from causal.cdl_trainer import CDLTrainer
    from causal.methods.cdl import CMIGraph
    from tests.causal.test_cdl import LAYOUT, TRUE, toy_batch

    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    trainer = CDLTrainer(LAYOUT, CDLConfig(feature_hidden=32, feature_dim=32, predictor_hidden=32, lr=3e-3), seed=0)
    for _ in range(250):
        trainer.update(*toy_batch(rng, 256))
    est = CMIGraph().estimate(trainer.model, *toy_batch(rng, 4_000), permute=torch.Generator().manual_seed(0))
    off = ~np.eye(*TRUE.shape, dtype=bool)
    found = fdr_graph(est, 0.05, 0.0, "permuted")
    assert np.array_equal(found, TRUE.astype(bool) & off), f"CMI:\n{np.round(est.cmi, 4)}\nnull:\n{np.round(est.null, 4)}"
    excess, se = est.excess()
    z = excess[~TRUE.astype(bool)] / np.where(se[~TRUE.astype(bool)] > 0, se[~TRUE.astype(bool)], 1)
    assert np.abs(z).max() < 4.0, np.round(z, 2)


def two_cluster_table(rng: np.random.Generator, bias_scale: float, edges: np.ndarray,
                      shape: tuple[int, int] = (15, 16)) -> tuple[EdgeEstimate, np.ndarray]:
    """A hand-made CMI table like a learned model's: non-edges biased above 0 (log-uniform over two
    decades up to ``bias_scale``, a third of them at 0), ``edges`` placed at random entries, standard
    errors a tenth of each entry's CMI (every nonzero entry significantly above 0)."""
    off = ~np.eye(*shape, dtype=bool)
    cmi = np.where(off, bias_scale * 10 ** rng.uniform(-2, 0, shape), 0.0)
    cmi[rng.random(shape) < 1 / 3] = 0.0
    truth = np.zeros(shape, dtype=bool)
    rows, cols = np.nonzero(off)
    pick = rng.choice(rows.size, edges.size, replace=False)
    truth[rows[pick], cols[pick]] = True
    cmi[rows[pick], cols[pick]] = edges
    stderr = np.where(cmi > 0, cmi / 10, 1e-6)
    return EdgeEstimate(cmi, stderr, 10_000), truth


@pytest.mark.parametrize("bias_scale", [2e-3, 5e-4, 1e-4])
def test_the_split_level_falls_between_two_clusters_and_follows_the_bias(bias_scale: float) -> None:
    """Weak edges a factor 3-6 above the largest biased non-edge, strong ones far above: the split cuts
    between the bias and the weak edges, whatever the bias's scale (a fixed min_cmi of 5e-3 misses
    the weak edges once they are below it), and the split graph is the true one."""
    rng = np.random.default_rng(11)
    edges = np.concatenate([bias_scale * np.array([3.0, 4.0, 6.0]), [0.05, 0.3, 0.8, 0.9]])
    est, truth = two_cluster_table(rng, bias_scale, edges)
    largest_non_edge = est.cmi[~truth].max()
    level = split_level(est, 0.05, cap=0.02)                # the cap decide passes: the method's threshold
    assert level is not None and largest_non_edge < level < edges.min()
    assert effect_level(est, 0.05, 5e-3, "split", cap=0.02) == level and effect_level(est, 0.05, 5e-3, "fixed") == 5e-3
    off = ~np.eye(*truth.shape, dtype=bool)
    assert np.array_equal(fdr_graph(est, 0.05, 5e-3, "split", cap=0.02) & off, truth)
    assert np.array_equal(decide(est, "fdr", 0.02, 0.05, 5e-3, bias="split")[0], truth)
    if bias_scale * 6 < 5e-3:
        assert not np.array_equal(fdr_graph(est, 0.05, 5e-3) & off, truth)


def test_no_two_clusters_falls_back_to_min_cmi() -> None:
    """One cluster (log-uniform CMIs, no gap of a factor 2), a single entry above a gap, too few
    significant entries, or none: ``split_level`` says there is no split and the rule tests against
    ``min_cmi``."""
    rng = np.random.default_rng(12)
    shape = (15, 16)
    off = ~np.eye(*shape, dtype=bool)
    smooth = np.where(off, np.exp(np.sort(rng.uniform(np.log(1e-5), np.log(1e-2), shape), axis=None).reshape(shape)), 0.0)
    gaps = np.diff(np.log(np.sort(smooth[off])))
    assert gaps.max() < np.log(2)                               # the table has no gap to cut at
    one = EdgeEstimate(smooth, smooth / 10, 10_000)
    assert split_level(one, 0.05) is None and effect_level(one, 0.05, 5e-3, "split") == 5e-3
    spread = one.cmi.copy()
    spread[0, 1] = 1.0                                         # one strong edge: a gap, but above the cap only
    assert split_level(EdgeEstimate(spread, spread / 10, 10_000), 0.05, cap=0.02) is None
    outlier = one.cmi.copy()
    outlier[outlier > 3e-3] = 3e-3
    outlier[0, 1] = 1e-2                                       # one entry 3x above the rest: not a cluster
    assert split_level(EdgeEstimate(outlier, outlier / 10, 10_000), 0.05, cap=0.02) is None
    outlier[0, 2] = 1.2e-2                                     # two of them: a cluster
    assert 3e-3 < split_level(EdgeEstimate(outlier, outlier / 10, 10_000), 0.05, cap=0.02) < 1e-2
    assert np.array_equal(fdr_graph(one, 0.05, 5e-3, "split"), fdr_graph(one, 0.05, 5e-3))
    few = np.zeros(shape)
    few[0, 1], few[2, 3] = 0.5, 1e-4
    assert split_level(EdgeEstimate(few, np.full(shape, 1e-6), 10_000), 0.05) is None
    noise = EdgeEstimate(rng.normal(0, 1e-3, shape), np.full(shape, 1e-3), 10_000)   # nothing above 0
    assert split_level(noise, 0.05) is None


def test_the_split_looks_below_the_fixed_threshold_only_and_marks_undecided_by_its_level() -> None:
    """Only strong edges (0.5-0.8 nats) above a bias cluster: with the cap at the method's 0.02 there is
    no gap below it, so the rule falls back to ``min_cmi``; without a cap the gap up to the strong edges
    is found. An entry whose interval reaches the level in use is undecided."""
    rng = np.random.default_rng(13)
    est, truth = two_cluster_table(rng, 1e-3, np.array([0.5, 0.6, 0.7, 0.8]))
    assert split_level(est, 0.05, cap=0.02) is None and 1e-3 < split_level(est, 0.05) < 0.5
    cmi, stderr = est.cmi.copy(), est.stderr.copy()
    j, i = np.argwhere(~truth & ~np.eye(*truth.shape, dtype=bool))[0]
    cmi[j, i], stderr[j, i] = 0.006, 0.002                     # not significantly above 5e-3; reaches it
    edges, undecided = decide(EdgeEstimate(cmi, stderr, 10_000), "fdr", 0.02, 0.05, 5e-3, bias="split")
    assert undecided[j, i] and not edges[j, i] and np.array_equal(edges, truth)
    assert undecided.sum() == 1


def test_the_mirror_level_by_hand() -> None:
    """Non-edges at +-1e-5 ... +-2e-4 (20 each side), one weak edge at 1e-3, 8 strong ones at 0.5. The
    tail is the largest tenth of the 20 negative magnitudes: 1.9e-4 (u) and 2e-4, so alpha = 1 / log(20 / 19)
    and V(2e-4) = (20 / 19)^-alpha = e^-1. At 0.15: t = 1.9e-4 counts 2 entries at or below -t against
    0.15 x 11 above, no; t = 2e-4 expects e^-1 = 0.37 <= 0.15 x 10, yes. At 0.02: 0.37 > 0.2, and the
    next magnitude, 1e-3, expects (1e-3 / 1.9e-4)^-alpha ~ e^-32: the level is the weak edge's."""
    shape = (7, 8)
    off = ~np.eye(*shape, dtype=bool)
    steps = np.arange(1, 21) * 1e-5
    cmi = np.zeros(shape)
    cmi[off] = np.concatenate([steps, -steps, [1e-3], np.full(off.sum() - 41, 0.5)])   # 49 entries: 8 strong
    est = EdgeEstimate(cmi, np.full(shape, 1e-5), 10_000)
    assert mirror_level(est, 0.15) == pytest.approx(2e-4)
    assert mirror_level(est, 0.02) == pytest.approx(1e-3)
    assert mirror_level(est, 0.02, cap=5e-4) == pytest.approx(5e-4)
    assert effect_level(est, 0.15, 5e-3, "mirror") == pytest.approx(2e-4)
    edges = fdr_graph(est, 0.15, 5e-3, "mirror")
    assert np.array_equal(edges, (cmi >= 2e-4 - 1e-12) & off)          # no test above the level: 2e-4 is in
    few = EdgeEstimate(np.where(off, np.abs(cmi), 0.0), est.stderr, 10_000)   # no negative side to mirror
    assert mirror_level(few, 0.05) is None and effect_level(few, 0.05, 5e-3, "mirror") == 5e-3
    assert np.array_equal(fdr_graph(few, 0.05, 5e-3, "mirror"), fdr_graph(few, 0.05, 5e-3))


def test_the_mirror_rule_holds_its_rate_on_symmetric_non_edges_and_finds_weak_edges() -> None:
    """Many tables whose non-edges are symmetric about 0 (heavy-tailed, a Student t with 3 degrees of
    freedom, scale 1e-4) with 25 edges, five weak (0.8e-3 to 2e-3, where the largest non-edges reach)
    and the rest strong: the rate reached averages close to the one requested and not above it by more
    than the spread of 200 tables allows, where the fixed ``min_cmi`` of 5e-3 reaches 0 and misses every
    weak edge. The mirror's level follows the non-edges' scale: a model trained longer (scale 2e-5)
    gets a lower level."""
    rng = np.random.default_rng(21)
    shape = (30, 31)
    off = ~np.eye(*shape, dtype=bool)
    rows, cols = np.nonzero(off)

    def table(scale: float) -> tuple[EdgeEstimate, np.ndarray]:
        cmi = np.where(off, scale * rng.standard_t(3, shape), 0.0)
        truth = np.zeros(shape, dtype=bool)
        pick = rng.choice(rows.size, 25, replace=False)
        truth[rows[pick], cols[pick]] = True
        cmi[rows[pick], cols[pick]] = np.concatenate([np.linspace(8e-4, 2e-3, 5), rng.uniform(0.02, 1.0, 20)])
        return EdgeEstimate(cmi, np.full(shape, scale), 10_000), truth

    for fdr in (0.05, 0.2):
        rates, weak_found, fixed_weak = [], [], []
        for _ in range(200):
            est, truth = table(1e-4)
            edges = fdr_graph(est, fdr, 5e-3, "mirror", cap=0.02)
            rates.append((edges & ~truth).sum() / max(edges.sum(), 1))
            weak = truth & (est.cmi < 5e-3)
            weak_found.append((edges & weak).sum() / weak.sum())
            fixed_weak.append((fdr_graph(est, fdr, 5e-3) & weak).sum())
        assert 0.4 * fdr < np.mean(rates) < 1.2 * fdr + 2 * np.std(rates) / np.sqrt(len(rates))
        assert np.mean(weak_found) > 0.5 and sum(fixed_weak) == 0
    coarse, fine = table(1e-4)[0], table(2e-5)[0]
    assert mirror_level(fine, 0.05) < mirror_level(coarse, 0.05)


def test_the_mirror_marks_undecided_by_its_level() -> None:
    """Under ``mirror`` an entry is undecided when it is no edge and its interval reaches the level."""
    rng = np.random.default_rng(22)
    shape = (15, 16)
    off = ~np.eye(*shape, dtype=bool)
    cmi = np.where(off, rng.normal(0, 1e-4, shape), 0.0)
    cmi[0:2, 2:12] = np.linspace(0.05, 0.5, 20).reshape(2, 10)   # 20 strong edges
    j, i = 3, 4
    cmi[j, i] = 0.0
    level = mirror_level(EdgeEstimate(cmi, np.full(shape, 1e-5), 10_000), 0.05)
    cmi[j, i] = 0.5 * level                                   # below the level, inside the negative side's reach
    assert mirror_level(EdgeEstimate(cmi, np.full(shape, 1e-5), 10_000), 0.05) == level
    stderr = np.full(shape, 1e-5)
    stderr[j, i] = level                                      # its interval reaches the level
    edges, undecided = decide(EdgeEstimate(cmi, stderr, 10_000), "fdr", 0.02, 0.05, 5e-3, bias="mirror")
    assert not edges[j, i] and undecided[j, i]
    assert level < 1e-3 and edges[0:2, 2:12].all() and edges.sum() == (cmi[off] >= level).sum()


def _biased_table(rng: np.random.Generator, scale: float = 1e-4) -> tuple[EdgeEstimate, np.ndarray]:
    """A table like a long-trained model's on a small graph: 25 edges (five weak, CMI 8e-4 to 2e-3,
    the rest strong), non-edges whose CMI is symmetric about 0 (Student t, 3 degrees of freedom) but
    for 30 the model leans on, whose CMI sits at 5e-4 to 3e-3, and a permuted null that takes off what
    the model's use of an input costs whatever value it reads: each non-edge's excess ``CMI - null``
    symmetric about 0 (its standard error ``scale``), an edge's its CMI plus the permutation's cost."""
    shape = (30, 31)
    off = ~np.eye(*shape, dtype=bool)
    rows, cols = np.nonzero(off)
    pick = rng.choice(rows.size, 55, replace=False)
    truth = np.zeros(shape, dtype=bool)
    truth[rows[pick[:25]], cols[pick[:25]]] = True
    cmi = np.where(off, scale * rng.standard_t(3, shape), 0.0)
    cmi[rows[pick[:25]], cols[pick[:25]]] = np.concatenate([np.linspace(8e-4, 2e-3, 5), rng.uniform(0.02, 1.0, 20)])
    cmi[rows[pick[25:]], cols[pick[25:]]] = rng.uniform(5e-4, 3e-3, 30)   # non-edges the model leans on
    excess = np.where(off, scale * rng.standard_t(3, shape), 0.0)
    excess[truth] = 2.0 * cmi[truth]
    stderr = np.full(shape, scale)
    return EdgeEstimate(cmi, stderr, 10_000, cmi - excess, stderr), truth


def test_mirror_permuted_holds_its_rate_where_the_non_edges_cmi_is_biased_above_zero() -> None:
    """Where some non-edges' CMI is biased above 0 (the model leans on them) the table's negative side
    no longer mirrors them: ``mirror`` lets them in, far past the rate requested. Their excess over the
    permuted null is symmetric again, so ``mirror-permuted`` reaches at most the rate requested (within
    the spread of 100 tables) and still finds most weak edges."""
    rng = np.random.default_rng(31)
    for fdr in (0.05, 0.2):
        mirror, permuted, weak_found = [], [], []
        for _ in range(100):
            est, truth = _biased_table(rng)
            for rates, bias in ((mirror, "mirror"), (permuted, "mirror-permuted")):
                edges = fdr_graph(est, fdr, 5e-3, bias, cap=0.02)
                rates.append((edges & ~truth).sum() / max(edges.sum(), 1))
            weak = truth & (est.cmi < 5e-3)
            weak_found.append((fdr_graph(est, fdr, 5e-3, "mirror-permuted", cap=0.02) & weak).sum() / weak.sum())
        assert np.mean(mirror) > 2 * fdr
        assert np.mean(permuted) < fdr + 2 * np.std(permuted) / np.sqrt(len(permuted))
        assert np.mean(weak_found) > 0.5


def test_mirror_permuted_takes_the_entries_above_both_levels_and_falls_back_without_a_negative_side() -> None:
    """The two levels are :func:`mirror_level`'s of the excess (capped) and of its z-score (not), the
    edges the entries at or above both, the report's level the excess's; no null or no negative side:
    the test of ``CMI > min_cmi``; undecided, the non-edges whose interval of the excess reaches it."""
    est, truth = _biased_table(np.random.default_rng(32))
    excess, stderr = est.cmi - est.null, est.excess_stderr
    level, z_level = mirror_permuted_levels(est, 0.05, cap=0.02)
    assert level == mirror_level(EdgeEstimate(excess, stderr, 0), 0.05, 0.02)
    assert z_level == mirror_level(EdgeEstimate(excess / stderr, np.ones_like(stderr), 0), 0.05)
    off = ~np.eye(*truth.shape, dtype=bool)
    edges = fdr_graph(est, 0.05, 5e-3, "mirror-permuted", cap=0.02)
    assert np.array_equal(edges, (excess >= level) & (excess / stderr >= z_level) & off)
    assert effect_level(est, 0.05, 5e-3, "mirror-permuted", cap=0.02) == level
    assert mirror_permuted_levels(EdgeEstimate(est.cmi, est.stderr, 0), 0.05) is None   # no null
    cap = mirror_permuted_levels(est, 0.05, cap=0.1 * level)
    assert cap[0] == pytest.approx(0.1 * level) and cap[1] == z_level
    one_sided = EdgeEstimate(est.cmi, est.stderr, 0, est.cmi - np.abs(excess), stderr)
    assert mirror_permuted_levels(one_sided, 0.05) is None
    assert np.array_equal(fdr_graph(one_sided, 0.05, 5e-3, "mirror-permuted"), fdr_graph(one_sided, 0.05, 5e-3))
    edges, undecided = decide(est, "fdr", 0.02, 0.05, 5e-3, bias="mirror-permuted")
    assert np.array_equal(undecided, ~edges & (excess + 1.96 * stderr >= level) & off)
