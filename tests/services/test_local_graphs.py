"""Live local-graph scoring: the evaluator scores the method's local graphs (CDL: point-wise CMI) of
held-out transitions against the simulator's true local graphs, and the run wires it up by itself
on the envs that score local graphs."""
from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from causal.graph_metrics import scored_entries
from proto.codec import decode, encode
from proto.messages import LocalGraphReport
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator import local as local_module
from services.graph_evaluator.core import GraphEvaluatorCore
from services.runtime.config import build_config
from services.supervisor import final_graph
from services.supervisor.config import RunConfig
from services.supervisor.wiring import resolve, scores_local_graphs, service_configs


def _trained(env: str, updates: int, **options) -> tuple[GraphEvaluatorCore, EnvWorkerCore]:
    torch.manual_seed(0)
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env=env, batch_steps=500, local_graphs=True, **options))
    learner = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, warmup_steps=200, cdl_feature_hidden=16,
                                               cdl_feature_dim=16, cdl_predictor_hidden=32), worker.spec)
    evaluator = GraphEvaluatorCore(GraphEvaluatorConfig(min_heldout=50, local_samples=300, local_examples=3,
                                                        heldout_fraction=0.3), worker.spec)
    for _ in range(8):
        batch = worker.collect()
        learner.ingest(batch)
        evaluator.ingest(batch)
    for _ in range(updates):
        learner.train_step()
    evaluator.load_weights(learner.weights())
    return evaluator, worker


def test_pointwise_cmi_local_graphs_are_scored_against_the_truth(tmp_path) -> None:
    evaluator, _ = _trained("chemical", 300, graph="chain", num_objects=3)
    assert evaluator.local is not None and evaluator.local_due
    report = decode(encode(evaluator.evaluate_local()), LocalGraphReport)  # it travels
    assert report.kind == "cdl" and report.estimator == "pcmi" and report.num_transitions == 300
    assert report.scores.shape == report.truth.shape == (3, 9, 10)
    m = report.metrics
    assert set(m) >= {"roc_auc", "pr_auc", "best_f1", "f1", "precision", "recall", "positive_rate"}
    assert m["roc_auc"] > 0.75, m  # an intervened object's colour is found after a short training
    interacting = (report.truth & scored_entries((9, 10))).any(axis=(1, 2))
    assert interacting[0] or not interacting.any()  # examples with an interaction come first
    assert not evaluator.local_due  # once per weights version
    evaluator.checkpoint(tmp_path / "ev.pt")
    again = GraphEvaluatorCore(evaluator.cfg, evaluator.spec)
    assert again.restore(tmp_path / "ev.pt")
    assert again.local.ring.size == evaluator.local.ring.size
    assert np.array_equal(again.local.ring.graphs[: again.local.ring.size],
                          evaluator.local.ring.graphs[: evaluator.local.ring.size])
    final = evaluator.evaluate_local(every=True)
    assert final.num_transitions == evaluator.local.ring.size


def test_the_final_local_graphs_in_chunks_score_as_one_call_and_report_progress(monkeypatch) -> None:
    evaluator, _ = _trained("chemical", 300, graph="chain", num_objects=3)
    whole = evaluator.evaluate_local(every=True)
    monkeypatch.setattr(local_module, "CHUNK", 64)
    seen: list[tuple[int, int]] = []
    chunked = evaluator.evaluate_local(every=True, progress=lambda done, total: seen.append((done, total)))
    n = evaluator.local.ring.size
    assert seen == [(min(done, n), n) for done in range(64, n + 64, 64)] and n % 64 and n > 64
    assert chunked.num_transitions == whole.num_transitions == n
    np.testing.assert_allclose(chunked.scores, whole.scores, rtol=1e-5, atol=1e-7)
    for key, value in whole.metrics.items():
        assert chunked.metrics[key] == pytest.approx(value, rel=1e-6, abs=1e-9), key
    stream = io.StringIO()
    lines = final_graph._progress_lines(stream, every_s=0.0)
    for done in (64, 128, 300):
        lines(done, 300)
    assert stream.getvalue().splitlines() == [f"final local graphs: {n} / 300 transitions (0s)" for n in (64, 128)]


def test_household_env_local_graphs_flow_into_the_evaluator() -> None:
    evaluator, worker = _trained("thawing", 50, task="thaw-fish")
    assert worker.spec.env_id == "thawing" and evaluator.local.ring.size > 0
    report = evaluator.evaluate_local()
    assert 0.0 < report.metrics["positive_rate"] < 0.1  # chapter 5: local dependencies are sparse


@pytest.mark.parametrize("env,options,expected", [
    ("chemical", {}, False),                                   # Chemical: only on request
    ("chemical", {"worker_local_graphs": True}, True),
    ("manipulation", {}, True),
    ("thawing", {"task": "thaw-olive"}, True),
    ("thawing", {"method": "modular"}, False),                 # no local-graph estimator
])
def test_the_run_asks_workers_for_local_graphs_where_they_are_scored(env: str, options: dict, expected: bool) -> None:
    cfg = resolve(build_config(RunConfig, router_port=7447, env=env, **options))
    assert scores_local_graphs(cfg) is expected
    assert service_configs(cfg, "x")["env-worker"].local_graphs is expected


def test_household_tasks_reach_the_env() -> None:
    cfg = resolve(build_config(RunConfig, router_port=7447, env="cleaning-car", task="clean-car", room_size=8))
    worker = EnvWorkerCore(service_configs(cfg, "x")["env-worker"])
    assert worker.env.unwrapped.task == "clean-car" and worker.env.unwrapped.config()["room_size"] == 8
    with pytest.raises(ValueError, match="poses no task 'thaw-fish'; its tasks: soak-rag, clean-car, clean-rag"):
        resolve(build_config(RunConfig, router_port=7447, env="cleaning-car", task="thaw-fish"))
    with pytest.raises(ValueError, match="room_size"):
        resolve(build_config(RunConfig, router_port=7447, env="thawing", room_size=3))


def test_a_batch_with_local_graphs_of_another_env_is_refused_and_nothing_is_kept() -> None:
    import dataclasses

    from proto.codec import ProtocolError

    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="thawing", batch_steps=64, local_graphs=True))
    evaluator = GraphEvaluatorCore(GraphEvaluatorConfig(heldout_fraction=0.5), worker.spec)
    batch = worker.collect()
    wrong = dataclasses.replace(batch, local_graph=np.zeros((64, 3, 4), np.uint8))
    with pytest.raises(ProtocolError, match="local graphs"):
        evaluator.ingest(wrong)
    assert evaluator.heldout.size == 0 and evaluator.local.ring.size == 0
    evaluator.ingest(batch)
    assert evaluator.local.ring.size == evaluator.heldout.size > 0
