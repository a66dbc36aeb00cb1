"""graph-evaluator core with a reward graph (CBM, ch. 4): reports carry the reward's scores and parents,
the minimal abstraction built from both graphs, and their scores against the env's truths."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from causal.abstraction import minimal_abstraction
from causal.cbm import CBMTrainer
from causal.cbm_config import CBMConfig
from causal.factored import FactorLayout
from causal.method import export_tensors
from envs.chemical_distractors import ChemicalDistractorsEnv
from proto.codec import decode, encode
from proto.messages import GraphReport, Weights
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore

torch.set_num_threads(1)
SMALL = CBMConfig(feature_hidden=8, feature_dim=8, predictor_hidden=16, embed_dim=8, candidate_hidden=16,
                  num_negatives=16, eval_negatives=64, cmi_samples=32)


def _spec():
    return ChemicalDistractorsEnv(graph="chain", num_objects=2, distractors="2,2").env_spec()


def _core(spec, **cfg) -> GraphEvaluatorCore:
    core = GraphEvaluatorCore(GraphEvaluatorConfig(method="cbm", min_heldout=32, eval_samples=64, **cfg), spec)
    return core


def test_a_report_from_the_true_graphs_scores_perfectly_and_keeps_the_true_minimal_abstraction() -> None:
    spec = _spec()
    core = _core(spec)
    core.cmi_ema, core.threshold = np.where(spec.global_graph == 1, 0.5, 1e-4).astype(np.float32), 0.02
    core.reward_ema, core.reward_threshold = np.where(spec.reward_parents == 1, 0.3, 0.0).astype(np.float32), 0.01
    core.weights = Weights(model="cbm", version=1, config_json="{}", env_steps=10, updates=1)
    report = decode(encode(core.report(num_heldout=100)), GraphReport)
    m = report.metrics
    assert m["f1"] == 1.0 and m["reward_f1"] == 1.0 and m["reward_accuracy"] == 1.0
    assert m["abstraction_accuracy"] == 1.0 == m["abstraction_accuracy_true_reward"]
    kept = report.controllable + report.action_relevant
    names = [spec.factor_names[j] for j in sorted(kept)]
    # no distractor, no position, and not obj1's colour: on a chain every action sets or re-samples it
    assert names == ["obj0.color", "obj0.goal_color", "obj1.goal_color"]
    assert report.reward_parents.tolist() == spec.reward_parents.tolist() == report.true_reward_parents.tolist()
    assert report.reward_threshold == 0.01 and report.reward_scores.dtype == np.float32
    assert m["true_abstraction_kept"] == 3.0 and m["abstraction_kept"] == 3.0


def test_without_reward_parents_nothing_is_kept_and_the_scores_say_so() -> None:
    spec = _spec()
    core = _core(spec)
    core.cmi_ema, core.threshold = np.where(spec.global_graph == 1, 0.5, 1e-4).astype(np.float32), 0.02
    core.reward_ema, core.reward_threshold = np.zeros(spec.num_factors + 1, np.float32), 0.01
    core.weights = Weights(model="cbm", version=1, config_json="{}", env_steps=10, updates=1)
    report = core.report(num_heldout=100)
    assert report.controllable + report.action_relevant == () and report.metrics["reward_recall"] == 0.0
    assert report.metrics["abstraction_accuracy"] == pytest.approx(1 - 3 / spec.num_factors)


def _transitions(spec, rows: int, seed: int):
    env = ChemicalDistractorsEnv(graph="chain", num_objects=2, distractors="2,2")
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    out = {k: [] for k in ("state", "action", "next_state", "reward")}
    for _ in range(rows):
        a = int(rng.integers(env.action_space.n))
        nxt, r, *_ = env.step(a)
        for k, v in zip(out, (obs, [a], nxt, r)):
            out[k].append(v)
        obs = nxt
    return {k: np.asarray(v, np.float32) for k, v in out.items()}


def test_live_and_final_evaluations_of_a_cbm_model_score_both_graphs_and_resume(tmp_path) -> None:
    spec = _spec()
    core = _core(spec)
    data = _transitions(spec, 64, 0)
    core.heldout.add(data["state"], data["action"], data["next_state"], data["reward"])
    trainer = CBMTrainer(FactorLayout.from_spec(spec), SMALL, seed=0)
    trainer.update(*(torch.from_numpy(data[k][:32]) for k in ("state", "action", "next_state", "reward")))
    core.load_weights(Weights(model="cbm", version=1, config_json=trainer.config_json(),
                              tensors=export_tensors(trainer.model), updates=1, env_steps=64))
    assert core.due and core.reward_threshold == SMALL.reward_threshold
    live = core.evaluate()
    assert live.reward_scores.shape == (spec.num_factors + 1,) and "reward_f1" in live.metrics
    abstraction = minimal_abstraction(live.adjacency, live.reward_parents)
    assert live.controllable + live.action_relevant == abstraction.controllable + abstraction.action_relevant
    core.checkpoint(tmp_path / "ev.pt")
    again = _core(spec)
    assert again.restore(tmp_path / "ev.pt")
    np.testing.assert_array_equal(again.reward_ema, core.reward_ema)
    final = core.evaluate_final()
    assert final.num_heldout == 64 and final.reward_parents is not None
    assert json.loads(json.dumps(final.metrics))  # plain floats
