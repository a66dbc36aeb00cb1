"""summary.json for a run with a reward graph (CBM): reward_graph, task_abstraction and the distractor
scores Table 4.1 needs, and the abstraction picture (Figs. 4.5-4.6)."""
from __future__ import annotations

import numpy as np
import pytest

from envs.chemical_distractors import ChemicalDistractorsEnv
from proto.messages import Weights
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.supervisor import report as reporting
from services.supervisor.report_reward import distractor_scores, plot_abstraction


def _report(reward_errors: bool = False, graph_errors: bool = False):
    spec = ChemicalDistractorsEnv(graph="chain", num_objects=2, distractors="2,2").env_spec()
    core = GraphEvaluatorCore(GraphEvaluatorConfig(method="cbm"), spec)
    cmi = np.where(spec.global_graph == 1, 0.5, 1e-4)
    if graph_errors:
        cmi[8, 0] = 0.3  # cd.0 <- obj0.color: a spurious edge into a distractor
    rewards = np.where(spec.reward_parents == 1, 0.3, 0.0)
    if reward_errors:
        rewards[1] = 0.05  # obj0.x taken for a reward parent
    core.cmi_ema, core.threshold = cmi.astype(np.float32), 0.02
    core.reward_ema, core.reward_threshold = rewards.astype(np.float32), 0.01
    core.weights = Weights(model="cbm", version=2, config_json="{}", env_steps=10, updates=1)
    return core.report(num_heldout=100)


def test_the_summary_has_the_reward_graph_the_task_abstraction_and_the_distractor_scores() -> None:
    content = reporting.summary(_report(reward_errors=True), {"run_id": "r"}, [])
    for block in (content, content["graph"]):
        reward = block["reward_graph"]
        assert reward["threshold"] == pytest.approx(0.01) and reward["scores"]["obj0.x"] == pytest.approx(0.05)
        assert reward["learned_parents"] == ["obj0.color", "obj0.x", "obj0.goal_color", "obj1.goal_color", "action"]
        assert "obj0.x" not in reward["true_parents"] and reward["recall"] == 1.0 and reward["precision"] < 1.0
    task = content["task_abstraction"]
    assert task["reward_parents"] == ["obj0.color", "obj0.x", "obj0.goal_color", "obj1.goal_color"]
    assert task["ancestors"] == [] and "cd.0" in task["dropped"] and "cd.0" in task["cdl_kept"]
    assert task["true_kept"] == ["obj0.color", "obj0.goal_color", "obj1.goal_color"]  # a chain overwrites obj1
    assert task["accuracy"] == pytest.approx(11 / 12) and task["accuracy_true_reward"] == 1.0
    assert content["distractors"]["count"] == 4 and content["distractors"]["non_distractor_f1"] == 1.0


def test_distractor_scores_put_the_empty_graph_beside_the_accuracy() -> None:
    report = _report(graph_errors=True)
    scores = distractor_scores(report.adjacency, report.true_graph, report.factor_names)
    assert scores["distractor_errors"] == 1 and scores["non_distractor_f1"] == 1.0
    assert scores["empty_graph_accuracy"] < scores["accuracy"] < 1.0
    assert scores["empty_graph_with_self_accuracy"] < scores["empty_graph_accuracy"]


def test_a_report_without_a_reward_graph_adds_nothing(tmp_path) -> None:
    report = _report()
    plain = type(report)(**{**report.__dict__, "reward_scores": None, "reward_parents": None,
                            "true_reward_parents": None})
    assert "reward_graph" not in reporting.graph_fields(plain)
    plot_abstraction(report, tmp_path / "abstraction.png")
    assert (tmp_path / "abstraction.png").stat().st_size > 1_000


def test_the_reward_scores_keep_their_small_entries() -> None:
    """The reward row's scores are written to significant digits, as the dynamics graph's CMI is: a
    score of 3.2e-6 nats is not 0 in the summary (5 decimals made it 0)."""
    report = _report()
    scores = report.reward_scores.copy()
    scores[2] = 3.21234e-6
    content = reporting.graph_fields(type(report)(**{**report.__dict__, "reward_scores": scores}))
    kept = content["reward_graph"]["scores"][list(report.factor_names)[2]]
    assert kept == pytest.approx(3.212e-6, rel=1e-9)
