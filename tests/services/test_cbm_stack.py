"""CBM through the unchanged in-process stack (``--method cbm`` on chemical-distractors): the learner
trains on rewards, the evaluator publishes graph reports with the reward's parents and the minimal
abstraction, and that abstraction is what the policy-learner masks its input with."""
from __future__ import annotations

import time

import numpy as np
import pytest

from causal.abstraction import minimal_abstraction
from proto import topics
from proto.codec import decode
from proto.messages import GraphReport, Weights
from services.policy_learner.config import PolicyLearnerConfig
from services.policy_learner.core import PolicyLearnerCore
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.inprocess import InProcessStack
from services.supervisor.wiring import learning_services, resolve

SMALL = dict(cbm_feature_hidden=8, cbm_feature_dim=8, cbm_predictor_hidden=16, cbm_embed_dim=8,
             cbm_candidate_hidden=16, cbm_reward_hidden=32, cbm_num_negatives=32, cbm_eval_negatives=128,
             cbm_cmi_samples=64)


def _collect(stack: InProcessStack, key: str, kind: type) -> list:
    found: list = []
    stack.transport().subscribe(key, lambda _, payload: found.append(decode(payload, kind)))
    return found


def test_cbm_runs_through_the_stack_and_reports_the_reward_graph(tmp_path) -> None:
    cfg = build_config(RunConfig, env="chemical-distractors", method="cbm", graph="chain", num_objects=2,
                       distractors="2,2", run_dir=str(tmp_path), run_id="cbm", learner_publish_every_s=0.3,
                       evaluator_min_interval_s=0.3, worker_max_steps_per_second=3000, progress=False, **SMALL)
    assert learning_services(cfg) == ("dynamics-learner", "graph-evaluator")
    stack = InProcessStack(cfg, config_overrides={"dynamics-learner": {"warmup_steps": 200},
                                                  "graph-evaluator": {"min_heldout": 50, "eval_samples": 200}})
    weights = _collect(stack, topics.weights("cbm", "cbm"), Weights)
    reports = _collect(stack, topics.graph("cbm", "cbm"), GraphReport)
    stack.start()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(reports) < 2:
            time.sleep(0.2)
    finally:
        stack.stop()
    assert weights and weights[-1].model == "cbm" and weights[-1].updates > 0
    assert len(reports) >= 2, "the evaluator published no graph report"
    last = reports[-1]
    d = len(last.factor_names)
    assert last.kind == "cbm" and d == 12 and last.cmi.shape == (d, d + 1)
    assert last.reward_scores.shape == (d + 1,) and last.reward_threshold == pytest.approx(0.01)
    assert last.true_reward_parents is not None and last.true_reward_parents.sum() == 4  # obj0's colour, goals, action
    assert {"reward_f1", "abstraction_accuracy", "abstraction_accuracy_true_reward", "f1"} <= set(last.metrics)
    kept = minimal_abstraction(last.adjacency, last.reward_parents)
    assert last.controllable == kept.controllable and last.action_relevant == kept.action_relevant


def test_the_policy_learner_masks_its_input_with_the_minimal_abstraction() -> None:
    from envs.chemical_distractors import ChemicalDistractorsEnv

    spec = ChemicalDistractorsEnv(graph="chain", num_objects=2, distractors="2,2").env_spec()
    abstraction = minimal_abstraction(spec.global_graph, spec.reward_parents)
    report = GraphReport(kind="cbm", weights_version=1, env_steps=0, updates=0, factor_names=spec.factor_names,
                         cmi=spec.global_graph.astype(np.float32), adjacency=spec.global_graph, threshold=0.02,
                         controllable=abstraction.controllable, action_relevant=abstraction.action_relevant,
                         action_irrelevant=abstraction.action_irrelevant,
                         reward_scores=spec.reward_parents.astype(np.float32), reward_parents=spec.reward_parents,
                         reward_threshold=0.01)
    core = PolicyLearnerCore(build_config(PolicyLearnerConfig, always_keep=""), spec)
    assert core.apply_graph(report)
    assert [spec.factor_names[j] for j in core.kept_factors] == ["obj0.color", "obj0.goal_color", "obj1.goal_color"]


def test_a_cbm_run_is_checked_like_any_other() -> None:
    cfg = resolve(build_config(RunConfig, env="chemical-distractors", method="cbm", distractors="20,20", router_port=7447))
    assert cfg.env == "chemical-distractors" and cfg.env_options.distractors == "20,20"
    with pytest.raises(ValueError, match="distractors must be"):
        build_config(RunConfig, env="chemical-distractors", method="cbm", distractors="20")
    with pytest.raises(ValueError, match="dynamics must be one of|implicit, explicit"):
        build_config(RunConfig, method="cbm", cbm_dynamics="both")
