"""The run's final graph: the final learner checkpoint's CMI on the evaluator's whole held-out set."""
from __future__ import annotations

import json

import numpy as np
import torch

from services.runtime.config import build_config
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.supervisor import report as reporting
from services.supervisor.final_graph import add_final_graph, final_graph


def test_final_graph_scores_the_last_checkpoint_on_every_heldout_transition(tmp_path) -> None:
    torch.set_num_threads(1)
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3, batch_steps=500))
    spec = worker.spec
    learner = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, warmup_steps=200), spec)
    evaluator_cfg = GraphEvaluatorConfig(min_heldout=50, eval_samples=50)
    evaluator = GraphEvaluatorCore(evaluator_cfg, spec)
    for _ in range(6):
        batch = worker.collect()
        learner.ingest(batch)
        evaluator.ingest(batch)
    for _ in range(30):
        learner.train_step()
    evaluator.load_weights(learner.weights())
    live = evaluator.evaluate()  # a live report: 50 draws, as the evaluator makes them
    for _ in range(30):
        learner.train_step()  # the learner trains on after the last live report
    checkpoints = tmp_path / "checkpoints"
    learner.checkpoint(checkpoints / "dynamics-learner-0.pt")
    evaluator.checkpoint(checkpoints / "graph-evaluator-0.pt")

    final = final_graph(tmp_path, evaluator_cfg, spec)
    n = evaluator.heldout.size
    assert final is not None and final.num_heldout == n > evaluator_cfg.eval_samples
    assert final.updates == learner.trainer.updates == 60 > live.updates
    held = (evaluator.heldout.state, evaluator.heldout.action, evaluator.heldout.next_state)
    expected = learner.trainer.model.cmi(*(torch.from_numpy(x[:n]) for x in held)).numpy()
    np.testing.assert_allclose(final.cmi, expected, rtol=1e-5, atol=1e-6)

    content = reporting.summary(live, {"run_id": "t"}, [])
    add_final_graph(content, final, tmp_path)
    block = json.loads(json.dumps(content))["final_graph"]
    assert block["num_heldout"] == n and block["graph_updates"] == 60
    assert block["f1"] == final.metrics["f1"] and np.array(block["cmi"]).shape == (9, 10)
    assert content["graph_updates"] == live.updates  # the live report's fields stay as they were
    assert (tmp_path / "graph.png").stat().st_size > 10_000 and (tmp_path / "object_graph.png").exists()


def test_final_graph_needs_both_checkpoints(tmp_path) -> None:
    spec = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3)).spec
    assert final_graph(tmp_path, GraphEvaluatorConfig(), spec) is None


def test_final_graph_command_refuses_what_is_not_a_finished_run(tmp_path, capsys) -> None:
    from services.cli import main

    assert main(["final-graph", "--run-dir", str(tmp_path)]) == 2
    assert "is not a finished run" in capsys.readouterr().err
