"""Local-graph reports in DashboardState: TP/FP/FN/TN per example, bounded history, runs with either kind."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from causal.graph_metrics import confusion
from proto.messages import LocalGraphReport
from services.dashboard.core import DashboardState
from services.dashboard.local_graph import predicted_graph
from tests.dashboard.reports import make_local_report, make_report

LOCAL_KEYS = {"kind", "estimator", "weights_version", "env_steps", "updates", "num_transitions", "timestamp",
              "received_at", "threshold", "factor_names", "cause_names", "metrics", "score_max", "num_examples",
              "examples", "history"}


def tiny_local(timestamp: float = 1.0, version: int = 1) -> LocalGraphReport:
    """Two factors, two transitions; the threshold is 0.1, a score equal to it counts as an edge."""
    #                            a     b     action
    scores = np.array([[[-0.3, 0.5, 0.01],     # a: self (scored low, drawn present), b -> a found, action missed
                        [0.1, 0.0, 0.2]],      # b: a -> b at the threshold (false), action -> b found
                       [[0.9, 0.05, 0.05],     # second transition: nothing found off the diagonal
                        [0.0, 2.0, 0.0]]], np.float32)
    truth = np.array([[[1, 1, 1], [0, 1, 1]],
                      [[1, 0, 0], [1, 1, 0]]], np.uint8)
    return LocalGraphReport(kind="cdl", estimator="pcmi", weights_version=version, env_steps=100 * version,
                            updates=10 * version, factor_names=("a", "b"), threshold=0.1, scores=scores,
                            truth=truth, metrics={"roc_auc": 0.75, "pr_auc": 0.6, "best_f1": 0.8,
                                                  "positive_rate": 0.5},
                            num_transitions=2, timestamp=timestamp)


def test_local_entries_are_classified_against_truth_at_the_threshold() -> None:
    state = DashboardState()
    assert state.add_local_report("r", tiny_local(), now=5.0)
    local = state.snapshot("r", now=6.0)["local_graph"]
    assert set(local) == LOCAL_KEYS
    first, second = local["examples"]
    assert first["outcomes"] == [["self", "tp", "fn"], ["fp", "self", "tp"]]
    assert first["predicted"] == [[1, 1, 0], [1, 1, 1]]  # self-edges drawn present whatever their score
    assert first["truth"] == [[1, 1, 1], [0, 1, 1]]
    assert first["scores"][0] == [pytest.approx(-0.3), pytest.approx(0.5), pytest.approx(0.01)]
    assert first["confusion"] == {"tp": 2, "fp": 1, "fn": 1, "tn": 0}
    assert second["outcomes"] == [["self", "tn", "tn"], ["fn", "self", "tn"]]
    assert second["confusion"] == {"tp": 0, "fp": 0, "fn": 1, "tn": 3}
    assert local["cause_names"] == ["a", "b", "action"] and local["threshold"] == 0.1
    assert local["estimator"] == "pcmi" and local["num_examples"] == 2 and local["score_max"] == 2.0
    assert local["metrics"]["roc_auc"] == 0.75 and local["received_at"] == 5.0
    assert local["history"] == [{"time": 1.0, "env_steps": 100, "updates": 10, "roc_auc": 0.75, "pr_auc": 0.6,
                                 "best_f1": 0.8, "f1": None, "precision": None, "recall": None,
                                 "positive_rate": 0.5}]


def test_counts_agree_with_the_graph_metrics_of_each_example() -> None:
    report = make_local_report(num_objects=3, examples=4, errors=4, seed=2)
    state = DashboardState()
    state.add_local_report("r", report, now=1.0)
    local = state.snapshot("r", now=1.0)["local_graph"]
    for k, example in enumerate(local["examples"]):
        assert example["confusion"] == confusion(report.scores[k] >= report.threshold, report.truth[k])
        assert len(example["scores"]) == 9 and all(len(row) == 10 for row in example["scores"])
        np.testing.assert_allclose(example["scores"], report.scores[k], rtol=1e-4)
    assert predicted_graph(report.scores[0], report.threshold).diagonal().all()


def test_examples_sent_are_capped_and_none_is_fine() -> None:
    state = DashboardState(local_examples=3)
    state.add_local_report("r", make_local_report(examples=10), now=1.0)
    local = state.snapshot("r", now=1.0)["local_graph"]
    assert len(local["examples"]) == 3 and local["num_examples"] == 10
    empty = replace(tiny_local(), scores=np.zeros((0, 2, 3), np.float32), truth=np.zeros((0, 2, 3), np.uint8))
    assert state.add_local_report("e", empty, now=2.0)
    local = state.snapshot("e", now=2.0)["local_graph"]
    assert local["examples"] == [] and local["num_examples"] == 0 and local["score_max"] == 0.1


def test_local_history_is_bounded_thinned_and_apart_from_the_graph_curve() -> None:
    state = DashboardState(history_points=10)
    for v in range(1, 26):
        assert state.add_local_report("r", tiny_local(timestamp=float(v), version=v), now=float(v))
    assert not state.add_local_report("r", tiny_local(timestamp=25.0, version=25), now=26.0)  # query + publication
    assert not state.add_local_report("r", tiny_local(timestamp=3.0, version=3), now=27.0)  # older, arrived late
    snapshot = state.snapshot("r", now=30.0)
    steps = [p["env_steps"] for p in snapshot["local_graph"]["history"]]
    assert len(steps) <= 10 and steps[0] == 100 and steps[-1] == 2500 and steps == sorted(steps)
    assert snapshot["graph"] is None and snapshot["history"] == []
    assert snapshot["local_graph"]["weights_version"] == 25 and snapshot["local_graph"]["received_at"] == 25.0


def test_runs_with_global_local_or_both_are_listed_and_kept_apart() -> None:
    state = DashboardState()
    state.add_report("global-only", make_report(2, version=2), now=1.0)
    state.add_local_report("local-only", make_local_report(3, version=4, kind="elden", estimator="grad"), now=2.0)
    state.add_report("both", make_report(3, version=5), now=3.0)
    state.add_local_report("both", make_local_report(3, version=5), now=4.0)
    runs = {r["run"]: r for r in state.runs(now=5.0)}
    assert [r["run"] for r in state.runs(now=5.0)] == ["both", "local-only", "global-only"]
    assert runs["local-only"]["has_local"] and not runs["local-only"]["has_graph"]
    assert runs["local-only"]["kind"] == "elden" and runs["local-only"]["local_weights_version"] == 4
    assert runs["local-only"]["f1"] is None and runs["local-only"]["local_roc_auc"] is not None
    assert not runs["global-only"]["has_local"] and runs["global-only"]["local_roc_auc"] is None
    assert runs["both"]["has_graph"] and runs["both"]["has_local"] and runs["both"]["updated_at"] == 4.0
    assert state.snapshot("global-only", 5.0)["local_graph"] is None
    assert state.snapshot("local-only", 5.0)["graph"] is None
    both = state.snapshot("both", 5.0)
    assert both["graph"]["weights_version"] == 5 and both["local_graph"]["weights_version"] == 5


def test_local_snapshots_are_strict_json_and_small() -> None:
    state = DashboardState()
    state.add_local_report("r", make_local_report(10, examples=12, errors=6), now=1.0)
    text = json.dumps(state.snapshot("r", 2.0), allow_nan=False)
    assert len(text) < 250_000  # 8 examples of 30 x 31 entries, pushed on every report


def test_bad_example_cap_is_refused() -> None:
    with pytest.raises(ValueError):
        DashboardState(local_examples=0)
