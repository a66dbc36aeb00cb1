"""Graph scores against hand-computed values."""
from __future__ import annotations

import numpy as np

from causal.graph_metrics import (
    average_precision,
    score_local_graphs,
    score_local_graphs_per_entry,
    best_threshold, binary_scores, confusion, identifiable_entries, roc_auc, score_graph, scored_entries,
)

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


def test_identifiable_scores_equal_the_full_ones_when_nothing_is_constant() -> None:
    scores = np.array([[9, 0.9, 0.1, 0.8], [0, 9, 0.3, 0.2], [0.25, 0.0, 9, 0.05]])
    paper = score_graph(scores, TRUTH, threshold=0.15)
    both = score_graph(scores, TRUTH, threshold=0.15, constant_factors=())
    assert not any(k.startswith("identifiable_") for k in paper)  # the paper's score alone, unchanged
    assert {k: v for k, v in both.items() if k in paper} == paper
    plain = {k: v for k, v in paper.items() if not k.startswith("with_self_")}
    assert {k: both[f"identifiable_{k}"] for k in plain} == plain
    assert both["unidentifiable_true_edges"] == 0.0
    assert np.array_equal(identifiable_entries(TRUTH.shape, ()), scored_entries(TRUTH.shape))


def test_identifiable_scores_leave_out_the_columns_of_constant_factors_by_hand() -> None:
    # Factor 1 is constant: its true edge 1 -> 0 is invisible to any learner, which misses it.
    # Full: tp 2 (0<-a, 1<-a), fp 1 (2<-0), fn 1 (0<-1), tn 5. Without column 1: tp 2, fp 1, fn 0, tn 4.
    cmi = np.array([[9, 0.0, 0.0, 0.8], [0.0, 9, 0.0, 0.6], [0.5, 0.0, 9, 0.0]])
    mask = identifiable_entries(TRUTH.shape, (1,))
    assert mask.sum() == 7 and not mask[:, 1].any() and mask[:, 3].all()
    s = score_graph(cmi, TRUTH, threshold=0.1, constant_factors=(1,))
    assert s["accuracy"] == 7 / 9 and s["recall"] == 2 / 3 and abs(s["f1"] - 2 / 3) < 1e-12
    assert s["identifiable_accuracy"] == 6 / 7 and s["identifiable_precision"] == 2 / 3
    assert s["identifiable_recall"] == 1.0 and abs(s["identifiable_f1"] - 0.8) < 1e-12
    assert s["unidentifiable_true_edges"] == 1.0
    # positives 0.8, 0.6 above all five negatives; the missed 1 -> 0 (CMI 0) only counts in the full AUC
    assert s["identifiable_roc_auc"] == 1.0 and s["roc_auc"] < 1.0


def test_with_self_scores_count_every_entry_with_the_self_edges_kept_by_hand() -> None:
    # Off the diagonal at 0.1: 0<-a (tp), 2<-0 (fp); missed 0<-1, 1<-a. Self-edges: 3 tp whatever the CMI.
    # Every entry: tp 4, fp 1, fn 2, tn 5 of 12.
    cmi = np.array([[-1.0, 0.0, 0.0, 0.8], [0.0, 0.0, 0.0, 0.01], [0.5, 0.0, -0.3, 0.0]])
    s = score_graph(cmi, TRUTH, threshold=0.1)
    assert s["with_self_accuracy"] == 9 / 12 and s["with_self_precision"] == 4 / 5
    assert s["with_self_recall"] == 4 / 6 and abs(s["with_self_f1"] - 8 / 11) < 1e-12
    # The plain scores of the same graph: tp 1, fp 1, fn 2, tn 5 of 9.
    assert s["accuracy"] == 6 / 9 and s["recall"] == 1 / 3
    # Over the finite (off-diagonal) values 0..0.8 the best is at 0.01, which keeps 1<-a too: tp 5, fp 1, fn 1.
    assert 0 < s["with_self_best_threshold"] <= 0.01 and abs(s["with_self_best_threshold_f1"] - 5 / 6) < 1e-12
    # Positives 0.8, 0.01, 0 (0<-1) and three self-edges at +inf against negatives 0 x 5 and 0.5:
    # 6 + 5 + 2.5 (ties) + 18 = 31.5 of 36 pairs.
    assert abs(s["with_self_roc_auc"] - 31.5 / 36) < 1e-12


def test_table_3_1_implies_self_edges_are_scored_on_manipulation() -> None:
    """The chapter's manipulation recall, precision and accuracy fit our truth only with self-edges counted."""
    from envs.manipulation_truth import global_graph

    truth = global_graph().astype(bool)
    recall, precision, accuracy = 0.612, 0.980, 0.902  # Table 3.1, CDL, manipulation

    def implied_accuracy(mask: np.ndarray) -> float:
        positives = truth[mask].sum()
        errors = positives * (1 - recall) + positives * recall * (1 / precision - 1)
        return 1 - errors / mask.sum()

    assert (truth.sum(), truth[scored_entries(truth.shape)].sum()) == (135, 112)
    assert abs(implied_accuracy(np.ones(truth.shape, bool)) - accuracy) < 0.001
    assert abs(implied_accuracy(scored_entries(truth.shape)) - accuracy) > 0.01


def test_exact_best_threshold_equals_trying_every_threshold() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        truth = rng.random((6, 7)) < 0.3
        scores = np.round(rng.normal(truth * 0.05, 0.03), 3)  # rounded: ties between entries
        mask = scored_entries(truth.shape)
        threshold, best = best_threshold(scores, truth)
        brute = max(binary_scores(scores >= t, truth)["f1"] for t in np.unique(scores[mask]))
        assert abs(best["f1"] - brute) < 1e-12
        assert best == binary_scores(scores >= threshold, truth)
        _, grid = best_threshold(scores, truth, num=200)
        assert best["f1"] >= grid["f1"] - 1e-12


def test_exact_best_threshold_resolves_weak_edges_a_coarse_grid_cannot() -> None:
    # One strong edge (5 nats) stretches a 200-step grid to 0.025-nat steps; the weak true edge
    # (0.012) sits between two non-edges (0.004, 0.02) within one step.
    truth = np.array([[1, 1, 1, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1, 1, 0], [0, 0, 0, 1, 0]], dtype=bool)
    scores = np.zeros(truth.shape)
    scores[0, 1], scores[0, 2], scores[2, 3] = 5.0, 0.03, 0.012
    scores[0, 3], scores[1, 0] = 0.004, 0.011
    threshold, best = best_threshold(scores, truth)
    assert threshold == 0.012 and best["f1"] == 1.0
    grid_threshold, grid = best_threshold(scores, truth, num=200)
    assert grid["f1"] < 1.0 and grid_threshold != threshold


def _brute_average_precision(scores: np.ndarray, truth: np.ndarray) -> float:
    """Sum over distinct thresholds (high to low) of precision x the recall it adds."""
    total, previous_recall = 0.0, 0.0
    for t in sorted(set(scores.tolist()), reverse=True):
        predicted = scores >= t
        precision = (predicted & truth).sum() / predicted.sum()
        recall = (predicted & truth).sum() / truth.sum()
        total += precision * (recall - previous_recall)
        previous_recall = recall
    return float(total)


def test_average_precision_by_hand_and_against_its_definition() -> None:
    one_row = np.array([[0.0, 0.9, 0.8, 0.7, 0.6]])  # entry 0 is the (unscored) self-edge
    truth = np.array([[1, 1, 0, 1, 0]], dtype=bool)
    assert average_precision(one_row, truth) == 0.5 * 1.0 + 0.5 * (2 / 3)
    tie = np.array([[0.0, 0.5, 0.5]])
    assert average_precision(tie, np.array([[1, 1, 0]], dtype=bool)) == 0.5  # a tie enters at once
    rng = np.random.default_rng(0)
    for _ in range(20):
        scores = rng.integers(0, 6, (6, 7)).astype(float)  # many ties
        truth = rng.random((6, 7)) < 0.3
        mask = scored_entries(truth.shape)
        if truth[mask].any():
            assert abs(average_precision(scores, truth) - _brute_average_precision(scores[mask], truth[mask])) < 1e-12


def test_local_graph_scores_pool_off_diagonal_entries_of_every_transition() -> None:
    rng = np.random.default_rng(1)
    truth = (rng.random((50, 4, 5)) < 0.2).astype(np.uint8)
    truth[:, np.arange(4), np.arange(4)] = 1
    perfect = score_local_graphs(truth.astype(float) * 2.0 - 1.0, truth, threshold=0.0)
    assert perfect["roc_auc"] == perfect["pr_auc"] == perfect["best_f1"] == perfect["f1"] == 1.0
    noise = score_local_graphs(rng.random(truth.shape), truth, threshold=0.5)
    off = truth[:, ~np.eye(4, 5, dtype=bool)]
    assert abs(noise["positive_rate"] - off.mean()) < 1e-12
    assert 0.35 < noise["roc_auc"] < 0.65 and noise["pr_auc"] < 0.4
    inverted = score_local_graphs(-(truth.astype(float)), truth, threshold=-0.5)
    assert inverted["roc_auc"] == 0.0 and inverted["f1"] == 0.0


def test_per_entry_scores_average_the_entries_whose_labels_vary_by_hand() -> None:
    truth = np.zeros((4, 2, 3), dtype=np.uint8)
    truth[:, 0, 1] = [1, 1, 0, 0]      # varies: scored
    truth[:, 1, 2] = [1, 0, 0, 0]      # varies: scored
    truth[:, 0, 2] = 1                 # always an edge: left out; diagonal entries are never scored
    scores = np.zeros(truth.shape)
    scores[:, 0, 1] = [0.9, 0.8, 0.1, 0.2]      # separates: ROC 1, AP 1, F1 1
    scores[:, 1, 2] = [1e-4, 2e-4, 3e-4, 0.0]   # the edge is 3rd of 4: ROC 1/3, AP 1/3, best F1 1/2
    got = score_local_graphs_per_entry(scores, truth)
    assert got["entries"] == 2
    assert abs(got["roc_auc"] - (1 + 1 / 3) / 2) < 1e-12
    assert abs(got["pr_auc"] - (1 + 1 / 3) / 2) < 1e-12
    assert abs(got["best_f1"] - (1 + 0.5) / 2) < 1e-12
    scaled = scores.copy()
    scaled[:, 1, 2] *= 1e4                      # per entry, an entry's scale does not matter; pooled, it does
    assert score_local_graphs_per_entry(scaled, truth) == got
    assert score_local_graphs(scaled, truth, 0.5)["roc_auc"] != score_local_graphs(scores, truth, 0.5)["roc_auc"]
