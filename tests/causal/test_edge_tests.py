"""CMI with a standard error and the FDR-tested graph (issue 22)."""
from __future__ import annotations

import numpy as np
import pytest

from causal.edge_tests import EdgeEstimate, benjamini_hochberg, decide, fdr_graph, p_values, undecided


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
