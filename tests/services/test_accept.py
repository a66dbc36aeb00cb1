"""What consumers accept (issue 20, item 3): versions move forward by bounded steps from the last
accepted one of their publisher, and weights whose model configuration is not the run's, or does not
describe the tensors they carry, are refused before any model is built. Real learner weights, real
evaluator, intrinsic-reward, learner and policy cores; one forged field at a time."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from causal.methods import model_from_config_json
from proto.codec import ProtocolError
from proto.messages import GraphReport
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator import core as evaluator_module
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.intrinsic_reward.core import IntrinsicRewardCore
from services.runtime.accept import MAX_VERSION_STEP, VersionGate
from services.runtime.config import build_config

SMALL = dict(cdl_feature_hidden=8, cdl_feature_dim=8, cdl_predictor_hidden=8, cdl_batch_size=16, warmup_steps=16)


@pytest.fixture(scope="module")
def learner() -> DynamicsLearnerCore:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3, batch_steps=64, seed=5))
    core = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **SMALL, seed=5), worker.spec)
    core.ingest(worker.collect())
    core.train_step()
    return core


def evaluator(learner: DynamicsLearnerCore) -> GraphEvaluatorCore:
    return GraphEvaluatorCore(build_config(GraphEvaluatorConfig, min_heldout=1, heldout_capacity=100), learner.spec)


def test_a_gate_takes_bounded_steps_and_keeps_its_last_version_on_a_jump() -> None:
    gate = VersionGate(max_step=10)
    assert gate.take("w", 5) and not gate.take("w", 5) and not gate.take("w", 4)
    assert gate.take("w", 15)
    with pytest.raises(ProtocolError, match="jumps more than 10 past the last accepted 15"):
        gate.take("w", 26)
    assert gate.last["w"] == 15 and gate.take("w", 16)
    assert gate.take("other", 10) and gate.last["w"] == 16  # per publisher
    assert VersionGate().max_step == MAX_VERSION_STEP


def test_the_evaluator_refuses_a_version_jump_and_goes_on_with_the_real_versions(learner: DynamicsLearnerCore) -> None:
    core = evaluator(learner)
    first = learner.weights()
    core.load_weights(first)
    forged = dataclasses.replace(learner.weights(), version=2**62, tensors={k: np.zeros_like(v) for k, v in first.tensors.items()})
    with pytest.raises(ProtocolError, match="jumps more than"):
        core.load_weights(forged)
    assert core.weights is first
    real = learner.weights()
    core.load_weights(real)
    assert core.weights is real and core.versions.last["cdl"] == real.version


def test_weights_naming_other_widths_are_refused_before_a_model_is_built(learner: DynamicsLearnerCore, monkeypatch) -> None:
    """The issue's 1.3 KB message whose configuration names large widths: refused from its size on
    the meta device; the evaluator never builds the (here 434 MiB) model."""
    built: list[str] = []

    def build(config_json: str) -> torch.nn.Module:
        if torch.empty(0).device.type != "meta":
            built.append(config_json)
        return model_from_config_json(config_json)

    monkeypatch.setattr(evaluator_module, "model_from_config_json", build)
    core = evaluator(learner)
    real = learner.weights()
    config = json.loads(real.config_json)
    config["cdl"].update(feature_hidden=1024, feature_dim=1024, predictor_hidden=1024)
    forged = dataclasses.replace(real, config_json=json.dumps(config, sort_keys=True))
    with pytest.raises(ValueError, match=r"describes 113,826,861 parameters, the message carries 1[0-9,]+; they differ"):
        core.load_weights(forged)
    assert built == [] and core.model is None and core.weights is None
    core.load_weights(real)
    assert built == [real.config_json] and core.weights is real


@pytest.mark.parametrize("field,value,match", [
    ("model", "modular", "weights of method 'modular', this run's is 'cdl'"),
    ("layout", {"names": ["x"]}, "another factor layout"),
])
def test_weights_of_another_method_or_layout_are_refused(learner: DynamicsLearnerCore, field: str, value: object,
                                                         match: str) -> None:
    real = learner.weights()
    config = json.loads(real.config_json)
    config[field] = value
    forged = dataclasses.replace(real, config_json=json.dumps(config))
    with pytest.raises(ValueError, match=match):
        evaluator(learner).load_weights(forged)
    scorer = IntrinsicRewardCore(build_config(IntrinsicRewardConfig), learner.spec)
    with pytest.raises(ValueError, match=match):
        scorer.load_weights(forged)
    assert scorer.model is None and scorer.load_weights(real)


def report(learner: DynamicsLearnerCore, version: int) -> GraphReport:
    n = learner.spec.num_factors
    return GraphReport(kind="cdl", weights_version=version, env_steps=0, updates=0,
                       factor_names=learner.spec.factor_names, cmi=np.zeros((n, n + 1), np.float32),
                       adjacency=np.ones((n, n + 1), np.uint8), threshold=0.02, controllable=(), action_relevant=(),
                       action_irrelevant=(), metrics={}, timestamp=0.0)


def test_graph_reports_that_jump_are_refused_by_the_learner_and_the_scorer(learner: DynamicsLearnerCore) -> None:
    scorer = IntrinsicRewardCore(build_config(IntrinsicRewardConfig), learner.spec)
    published, learner.version = learner.version, 3 + MAX_VERSION_STEP + 1  # the learner published these
    try:
        for consumer in (learner, scorer):
            assert consumer.apply_graph(report(learner, 3))
            with pytest.raises(ProtocolError, match="jumps more than"):
                consumer.apply_graph(report(learner, 3 + MAX_VERSION_STEP + 1))
            assert consumer.graph_version == 3 and consumer.apply_graph(report(learner, 4))
    finally:
        learner.version = published


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_policy_weights_naming_other_widths_are_refused_before_the_policy_is_built(algo: str) -> None:
    from gymnasium import spaces

    from services.env_worker.core import PolicyActor
    from services.policy_learner.config import PolicyLearnerConfig
    from services.policy_learner.core import PolicyLearnerCore
    from tests.services.test_graph_evaluator_core import _manipulation_spec

    spec = _manipulation_spec() if algo == "sac" else EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3)).spec
    real = PolicyLearnerCore(PolicyLearnerConfig(algo=algo, hidden=16), spec).weights()
    space = spaces.Box(-1.0, 1.0, (spec.action_size,)) if algo == "sac" else spaces.Discrete(spec.action_size)
    actor = PolicyActor(spec.state_dim, 0, space)
    config = json.loads(real.config_json)
    config["hidden"] = [8192, 8192]
    with pytest.raises(ValueError, match="the policy configuration describes .* parameters, the message carries"):
        actor.load(dataclasses.replace(real, config_json=json.dumps(config)))
    assert actor.agent is None and actor.load(real) and actor.version == real.version
