"""CMI with a standard error and the FDR-tested graph (issue 22)."""
from __future__ import annotations

import numpy as np

from causal.edge_tests import EdgeEstimate, benjamini_hochberg, fdr_graph, p_values, undecided


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
