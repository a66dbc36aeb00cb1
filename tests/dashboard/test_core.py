"""DashboardState: cell classification, bounded history, several runs, service beats, JSON-able snapshots."""
from __future__ import annotations

import json

import numpy as np
import pytest

from causal.graph_metrics import confusion
from proto.messages import GraphReport
from services.dashboard.cells import classify
from services.dashboard.core import DashboardState
from tests.dashboard.reports import factor_names, make_report, make_stats


def tiny_report(timestamp: float = 1.0, version: int = 1) -> GraphReport:
    """Two factors: one cell of each outcome off the diagonal."""
    #                  a  b  action          a  b  action
    learned = np.array([[1, 1, 0], [1, 0, 1]], np.uint8)
    truth = np.array([[1, 1, 1], [0, 1, 0]], np.uint8)
    cmi = np.array([[0.5, 0.3, 0.001], [0.04, 0.01, 0.2]], np.float32)
    return GraphReport(kind="cdl", weights_version=version, env_steps=100 * version, updates=10 * version,
                       factor_names=("a", "b"), cmi=cmi, adjacency=learned, threshold=0.02, controllable=(0,),
                       action_relevant=(), action_irrelevant=(1,), metrics={"f1": 0.5, "accuracy": 0.5},
                       true_graph=truth, num_heldout=10, timestamp=timestamp)


def test_cells_are_classified_tp_fp_fn_tn_with_self_edges_apart() -> None:
    state = DashboardState()
    assert state.add_report("r", tiny_report(), now=5.0)
    graph = state.snapshot("r", now=6.0)["graph"]
    outcomes = [[c["outcome"] for c in row] for row in graph["cells"]]
    assert outcomes == [["self", "tp", "fn"], ["fp", "self", "fp"]]
    assert graph["confusion"] == {"tp": 1, "fp": 2, "fn": 1, "tn": 0}
    assert graph["cells"][1][0] == {"cmi": pytest.approx(0.04), "learned": True, "truth": False, "outcome": "fp"}
    assert graph["cause_names"] == ["a", "b", "action"] and graph["threshold"] == 0.02
    assert graph["classes"][0] == {"key": "controllable", "label": "Controllable",
                                   "factors": [{"index": 0, "name": "a"}]}
    assert [c["key"] for c in graph["classes"]] == ["controllable", "action_relevant", "action_irrelevant"]


def test_counts_agree_with_the_graph_metrics_and_cmi_survives_rounding() -> None:
    report = make_report(num_objects=3, errors=5, seed=3)
    state = DashboardState()
    state.add_report("r", report, now=1.0)
    graph = state.snapshot("r", now=1.0)["graph"]
    assert graph["confusion"] == confusion(report.adjacency, report.true_graph)
    cmi = np.array([[c["cmi"] for c in row] for row in graph["cells"]])
    np.testing.assert_allclose(cmi, report.cmi, rtol=1e-4)
    assert len(graph["cells"]) == 9 and all(len(row) == 10 for row in graph["cells"])
    named = {c["key"]: [f["name"] for f in c["factors"]] for c in graph["classes"]}
    assert named["controllable"] == [factor_names(3)[i] for i in report.controllable]
    assert graph["metrics"]["f1"] == report.metrics["f1"]


def test_without_ground_truth_cells_are_unclassified() -> None:
    report = make_report(num_objects=2, with_truth=False)
    state = DashboardState()
    state.add_report("r", report, now=1.0)
    snapshot = state.snapshot("r", now=1.0)
    assert snapshot["graph"]["confusion"] is None
    assert {c["outcome"] for row in snapshot["graph"]["cells"] for c in row} == {"self", None}
    assert snapshot["history"][0]["f1"] is None
    assert classify(report.adjacency, None)[0][0] == "self"


def test_history_is_bounded_and_thinned_so_it_still_spans_the_run() -> None:
    state = DashboardState(history_points=10)
    for v in range(1, 26):
        assert state.add_report("r", tiny_report(timestamp=float(v), version=v), now=float(v))
    history = state.snapshot("r", now=30.0)["history"]
    assert len(history) <= 10
    steps = [p["env_steps"] for p in history]
    assert steps[0] == 100 and steps[-1] == 2500 and steps == sorted(steps)
    assert set(history[0]) == {"time", "env_steps", "updates", "f1", "accuracy", "precision", "recall", "roc_auc",
                               "best_threshold_f1", "identifiable_f1", "with_self_best_threshold_f1",
                               "with_self_accuracy", "reward_f1", "abstraction_accuracy"}
    assert history[0]["precision"] is None and history[0]["f1"] == 0.5


def test_duplicate_and_late_reports_are_ignored() -> None:
    state = DashboardState()
    assert state.add_report("r", tiny_report(timestamp=10.0, version=3), now=1.0)
    assert not state.add_report("r", tiny_report(timestamp=10.0, version=3), now=2.0)  # query reply + publication
    assert not state.add_report("r", tiny_report(timestamp=9.0, version=2), now=3.0)  # older, arrived late
    snapshot = state.snapshot("r", now=4.0)
    assert snapshot["graph"]["weights_version"] == 3 and len(snapshot["history"]) == 1
    assert snapshot["graph"]["received_at"] == 1.0


def test_several_runs_are_kept_apart_and_listed_newest_graph_first() -> None:
    state = DashboardState(max_runs=3)
    state.add_report("old", make_report(2, version=1), now=1.0)
    state.add_report("new", make_report(3, version=7), now=2.0)
    state.add_stats("beats-only", make_stats("env-worker"), now=3.0)
    runs = state.runs(now=4.0)
    assert [r["run"] for r in runs] == ["new", "old", "beats-only"]
    assert runs[0]["weights_version"] == 7 and runs[0]["has_graph"] and runs[0]["kind"] == "cdl"
    assert runs[2] == {"run": "beats-only", "has_graph": False, "kind": None, "weights_version": None,
                       "env_steps": None, "f1": None, "has_local": False, "local_weights_version": None,
                       "local_roc_auc": None, "updated_at": None, "last_seen": 3.0, "services": 1}
    assert len(state.snapshot("old", 4.0)["graph"]["factor_names"]) == 6
    assert len(state.snapshot("new", 4.0)["graph"]["factor_names"]) == 9
    assert state.snapshot("beats-only", 4.0)["graph"] is None
    assert state.snapshot("beats-only", 4.0)["local_graph"] is None
    assert state.snapshot("nope", 4.0) is None and state.services("nope", 4.0) is None
    state.add_report("newest", make_report(2), now=5.0)  # a fourth run: "old" was seen longest ago
    assert sorted(state.run_ids()) == ["beats-only", "new", "newest"]


def test_service_beats_keep_the_latest_per_instance_and_go_stale() -> None:
    state = DashboardState(max_services=2, stale_after_s=10.0)
    state.add_stats("r", make_stats("env-worker", "0", env_steps=1), now=1.0)
    state.add_stats("r", make_stats("env-worker", "0", env_steps=2), now=2.0)
    state.add_stats("r", make_stats("dynamics-learner", "0", updates=5), now=8.0)
    services = state.services("r", now=15.0)
    assert [(s["service"], s["instance"]) for s in services] == [("dynamics-learner", "0"), ("env-worker", "0")]
    worker = services[1]
    assert worker["values"] == {"env_steps": 2.0} and worker["last_seen"] == 2.0
    assert worker["age_s"] == 13.0 and worker["stale"] and not services[0]["stale"]
    state.add_stats("r", make_stats("graph-evaluator", "0"), now=16.0)  # over max_services: oldest beat goes
    assert [s["service"] for s in state.services("r", now=16.0)] == ["dynamics-learner", "graph-evaluator"]


def test_snapshots_are_strict_json() -> None:
    state = DashboardState()
    state.add_report("r", make_report(10, errors=6), now=1.0)
    state.add_stats("r", make_stats("env-worker", env_steps=3.0), now=1.0)
    text = json.dumps({"snapshot": state.snapshot("r", 2.0), "runs": state.runs(2.0)}, allow_nan=False)
    assert len(text) < 200_000  # 30 x 31 cells stay small enough to push on every report


def test_bad_bounds_are_refused() -> None:
    with pytest.raises(ValueError):
        DashboardState(history_points=1)


def test_a_reward_graph_adds_a_reward_row_and_the_minimal_abstraction() -> None:
    from tests.dashboard.reports import make_reward_report

    report = make_reward_report(num_objects=3, reward_errors=2)
    state = DashboardState()
    state.add_report("r", report, now=1.0)
    snapshot = state.snapshot("r", now=1.0)
    graph = snapshot["graph"]
    reward = graph["reward"]
    assert reward["row_name"] == "reward" and len(reward["cells"]) == 10 and reward["threshold"] == 0.01
    assert [c["outcome"] for c in reward["cells"]][:3] == ["tp", "fp", "fp"]  # obj0: colour, then x and y
    assert reward["confusion"] == {"tp": 4, "fp": 2, "fn": 0, "tn": 4}
    assert all(c["threshold"] == 0.01 for c in reward["cells"])
    assert len(graph["cells"]) == 9 and graph["abstraction"] == "minimal"
    assert [c["key"] for c in graph["classes"]] == ["reward_parents", "reward_ancestors", "dropped"]
    named = {c["key"]: [f["name"] for f in c["factors"]] for c in graph["classes"]}
    kept = set(report.controllable + report.action_relevant)
    assert set(named["reward_parents"]) | set(named["reward_ancestors"]) == {report.factor_names[j] for j in kept}
    assert "obj0.x" in named["reward_parents"]
    assert snapshot["history"][-1]["reward_f1"] == pytest.approx(report.metrics["reward_f1"], rel=1e-4)
    assert snapshot["history"][-1]["abstraction_accuracy"] is not None
    json.dumps(snapshot, allow_nan=False)
    state.add_report("c", make_report(num_objects=3), now=2.0)
    cdl = state.snapshot("c", now=2.0)["graph"]
    assert cdl["reward"] is None and cdl["abstraction"] == "cdl"
    assert state.snapshot("c", now=2.0)["history"][-1]["reward_f1"] is None


def test_cells_carry_standard_errors_and_undecided_entries_where_the_report_has_them() -> None:
    from dataclasses import replace

    state = DashboardState()
    plain = state.add_report("r", tiny_report(), now=5.0) and state.snapshot("r", now=6.0)["graph"]
    assert "stderr" not in plain["cells"][0][1] and plain["undecided"] is None and plain["edge_rule"] == "fixed"
    undecided = np.zeros((2, 3), np.uint8)
    undecided[1, 1 - 1] = 1
    tested = replace(tiny_report(timestamp=2.0, version=2), cmi_stderr=np.full((2, 3), 0.01, np.float32),
                     undecided=undecided, edge_rule="fdr", fdr=0.05, min_cmi=5e-4)
    assert state.add_report("r", tested, now=7.0)
    graph = json.loads(json.dumps(state.snapshot("r", now=8.0)["graph"]))
    assert graph["cells"][1][0] == {"cmi": pytest.approx(0.04), "learned": True, "truth": False, "outcome": "fp",
                                    "stderr": pytest.approx(0.01), "undecided": True}
    assert (graph["edge_rule"], graph["fdr"], graph["min_cmi"], graph["undecided"]) == ("fdr", 0.05, 5e-4, 1)


def test_the_reward_row_carries_its_standard_errors_and_undecided_entries() -> None:
    from dataclasses import replace

    from tests.dashboard.reports import make_reward_report

    plain = make_reward_report(num_objects=3, reward_errors=2)
    state = DashboardState()
    state.add_report("r", plain, now=1.0)
    reward = state.snapshot("r", now=1.0)["graph"]["reward"]
    assert reward["undecided"] is None and all("stderr" not in c and "undecided" not in c for c in reward["cells"])
    stderr = np.linspace(1e-4, 1e-2, 10).astype(np.float32)
    undecided = np.zeros(10, np.uint8)
    undecided[[1, 4]] = 1
    tested = replace(plain, weights_version=2, timestamp=plain.timestamp + 1, reward_stderr=stderr,
                     reward_undecided=undecided)
    assert state.add_report("r", tested, now=2.0)
    reward = json.loads(json.dumps(state.snapshot("r", now=2.0)["graph"]["reward"]))
    assert [c["stderr"] for c in reward["cells"]] == pytest.approx(stderr.tolist(), rel=1e-4)
    assert [c["undecided"] for c in reward["cells"]] == [False, True, False, False, True] + [False] * 5
    assert reward["undecided"] == 2


def test_cells_carry_the_permuted_null_and_the_graph_its_bias() -> None:
    from dataclasses import replace

    state = DashboardState()
    state.add_report("r", tiny_report(), now=1.0)
    plain = state.snapshot("r", now=1.0)["graph"]
    assert plain["bias"] == "fixed" and all("null" not in c for row in plain["cells"] for c in row)
    null = np.array([[0.0, 2e-3, 1e-4], [3e-3, 0.0, 5e-4]], np.float32)
    tested = replace(tiny_report(timestamp=2.0, version=2), cmi_stderr=np.full((2, 3), 0.01, np.float32),
                     undecided=np.zeros((2, 3), np.uint8), edge_rule="fdr", fdr=0.05, min_cmi=5e-3,
                     bias="pooled", cmi_null=null)
    assert state.add_report("r", tested, now=2.0)
    graph = json.loads(json.dumps(state.snapshot("r", now=2.0)["graph"]))
    assert graph["bias"] == "pooled"
    assert [c["null"] for row in graph["cells"] for c in row] == pytest.approx(null.ravel().tolist(), rel=1e-4)
