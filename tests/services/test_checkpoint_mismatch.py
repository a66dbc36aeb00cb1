"""A run directory's checkpoint made for another configuration is refused with a clear error."""
from __future__ import annotations

import pytest
import torch

from services.runtime.config import build_config
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.runtime.checkpoint import CheckpointMismatch, load_checkpoint
from services.supervisor.evaluation import model_from_checkpoint


def spec(graph: str):
    return EnvWorkerCore(build_config(EnvWorkerConfig, graph=graph, num_objects=3)).spec


def test_learner_refuses_another_model_or_env(tmp_path) -> None:
    path = tmp_path / "learner.pt"
    small = build_config(DynamicsLearnerConfig, cdl_feature_hidden=8, cdl_feature_dim=8, cdl_predictor_hidden=8)
    DynamicsLearnerCore(small, spec("chain")).checkpoint(path)
    assert DynamicsLearnerCore(small, spec("chain")).restore(path)
    with pytest.raises(CheckpointMismatch, match="different environment or model"):
        DynamicsLearnerCore(build_config(DynamicsLearnerConfig, cdl_feature_hidden=16, cdl_feature_dim=8, cdl_predictor_hidden=8),
                            spec("chain")).restore(path)
    with pytest.raises(CheckpointMismatch):
        DynamicsLearnerCore(small, spec("collider")).restore(path)


def test_learner_resumes_under_another_learning_rate_schedule(tmp_path) -> None:
    path = tmp_path / "learner.pt"
    small = dict(cdl_feature_hidden=8, cdl_feature_dim=8, cdl_predictor_hidden=8)
    DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **small), spec("chain")).checkpoint(path)
    decayed = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **small, cdl_lr_decay_updates=500, cdl_lr_final=2e-4), spec("chain"))
    assert decayed.restore(path) and decayed.trainer.lr == decayed.trainer.cfg.lr_at(0)
    decayed.checkpoint(path)  # the final model (a run's summary) is rebuilt with the schedule it ran under
    rebuilt = model_from_checkpoint(load_checkpoint(path))
    assert (rebuilt.cfg.lr_decay_updates, rebuilt.cfg.lr_final) == (500, 2e-4)


def test_learner_resumes_in_another_training_precision(tmp_path) -> None:
    """The weights are fp32 in either precision, so a run trained with fp32 products may go on in bf16."""
    path = tmp_path / "learner.pt"
    small = dict(cdl_feature_hidden=8, cdl_feature_dim=8, cdl_predictor_hidden=8)
    fp32 = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **small), spec("chain"))
    fp32.checkpoint(path)
    bf16 = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **small, cdl_train_precision="bf16"), spec("chain"))
    assert bf16.restore(path) and bf16.trainer.cfg.train_precision == "bf16"
    for name, tensor in bf16.trainer.model.state_dict().items():
        assert torch.equal(tensor, fp32.trainer.model.state_dict()[name]), name


def test_evaluator_refuses_another_env(tmp_path) -> None:
    path = tmp_path / "evaluator.pt"
    GraphEvaluatorCore(GraphEvaluatorConfig(), spec("chain")).checkpoint(path)
    assert GraphEvaluatorCore(GraphEvaluatorConfig(), spec("chain")).restore(path)
    with pytest.raises(CheckpointMismatch):
        GraphEvaluatorCore(GraphEvaluatorConfig(), spec("full")).restore(path)
