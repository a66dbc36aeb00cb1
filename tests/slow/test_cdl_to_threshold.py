"""Train-to-threshold: the service cores, wired without a bus, learn Chemical graphs to the paper's F1.

Slow (minutes): run with `make test-slow`. The same numbers through the real stack come from
`make bench-f1` (README, "Reproducing the figures").
"""
from __future__ import annotations

import time

import pytest
import torch

from services.runtime.config import build_config
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore

pytestmark = pytest.mark.slow


def learn(graph: str, num_objects: int, metric: str, target: float, budget_s: float) -> dict[str, float]:
    torch.set_num_threads(1)
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, graph=graph, num_objects=num_objects, batch_steps=512))
    learner = DynamicsLearnerCore(DynamicsLearnerConfig(), worker.spec)
    evaluator = GraphEvaluatorCore(GraphEvaluatorConfig(), worker.spec)
    started, scores = time.monotonic(), {}
    while time.monotonic() - started < budget_s:
        batch = worker.collect()
        learner.ingest(batch)
        evaluator.ingest(batch)
        for _ in range(20 if learner.ready else 0):
            learner.train_step()
        if learner.trainer.updates and learner.trainer.updates % 500 == 0:
            evaluator.load_weights(learner.weights())
            report = evaluator.evaluate()
            learner.apply_graph(report)
            scores = report.metrics
            if scores[metric] >= target:
                break
    return scores


def test_chain_reaches_f1_one() -> None:
    scores = learn("chain", 10, "f1", 1.0, budget_s=600)
    assert scores["f1"] == 1.0, scores


def test_collider_reaches_f1_one() -> None:
    scores = learn("collider", 10, "best_threshold_f1", 1.0, budget_s=600)
    assert scores["best_threshold_f1"] == 1.0, scores
