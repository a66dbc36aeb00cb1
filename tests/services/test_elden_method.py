"""ELDEN through the unchanged services: prioritised replay in the dynamics-learner, its rewards in the
intrinsic-reward service (warm-up, curiosity), the run's checks, and a live in-process run on Thawing
that publishes Jacobian local-graph reports."""
from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from causal.elden_graphs import graph_variance
from causal.methods import get_method
from causal.replay import PrioritisedReplay
from proto import topics
from proto.codec import decode
from proto.messages import LocalGraphReport, Weights
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.intrinsic_reward.core import IntrinsicRewardCore
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.inprocess import InProcessStack
from services.supervisor.wiring import resolve

TINY = dict(elden_members=2, elden_token_hidden=8, elden_embed_dim=8, elden_heads=2, elden_predictor_hidden=8,
            elden_member_batch=8)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def thawing() -> tuple[EnvWorkerCore, list]:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="thawing", batch_steps=300, local_graphs=True))
    return worker, [worker.collect() for _ in range(2)]


def learner(thawing, **settings) -> DynamicsLearnerCore:
    worker, batches = thawing
    core = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, method="elden", warmup_steps=50, **TINY,
                                            **settings), worker.spec)
    for batch in batches:
        core.ingest(batch)
    return core


def test_prioritised_learner_gives_sampled_rows_the_trainers_priorities(thawing, tmp_path) -> None:
    core = learner(thawing, elden_prioritised=True)
    assert isinstance(core.replay, PrioritisedReplay) and get_method("elden").prioritised
    before = core.replay.probabilities().copy()
    np.testing.assert_allclose(before, before[0])  # every row starts at the largest priority
    core.train_step()
    assert core.last_stats["nll_full"] > 0 and core.trainer.last_priorities.shape == (16,)
    given = np.linspace(0.1, 0.5, 16)  # an untrained model's priorities are all ~1: summed cross-entropy is large
    core.trainer.priorities = lambda x, targets: given
    core.train_step()
    changed = core.replay.priorities.get(np.arange(core.replay.size))
    assert 8 <= (changed < 1.0).sum() <= 16 and set(changed[changed < 1.0]) <= set(given)
    core.checkpoint(tmp_path / "learner.pt")
    again = learner(thawing, elden_prioritised=True)
    assert again.restore(tmp_path / "learner.pt")
    np.testing.assert_allclose(again.replay.probabilities(), core.replay.probabilities())


def test_without_the_flag_the_learner_samples_uniformly(thawing) -> None:
    core = learner(thawing)
    for _ in range(2):
        core.train_step()
    assert core.trainer.last_priorities is None
    np.testing.assert_allclose(core.replay.probabilities(), 1.0 / core.replay.size)
    weights = core.weights()
    assert weights.model == "elden" and weights.updates == 2


def _weights(core: DynamicsLearnerCore, env_steps: int) -> Weights:
    weights = core.weights()
    return Weights(model=weights.model, version=weights.version, config_json=weights.config_json,
                   tensors=weights.tensors, updates=weights.updates, env_steps=env_steps)


def test_elden_reward_waits_for_its_warm_up_then_is_the_graph_variance(thawing) -> None:
    worker, batches = thawing
    core = learner(thawing, elden_reward_warmup_env_steps=1000)
    core.train_step()
    reward = IntrinsicRewardCore(IntrinsicRewardConfig(method="elden", reward="elden", eta=2.0), worker.spec)
    batch = batches[0]
    assert reward.load_weights(_weights(core, env_steps=999))
    assert (reward.score(batch).intrinsic_reward == 0).all()  # warm-up: weights have seen too few steps
    assert reward.load_weights(_weights(core, env_steps=1000))
    scored = reward.score(batch)
    s, a, n = (torch.from_numpy(x) for x in (batch.state, batch.action, batch.next_state))
    expected = 2.0 * graph_variance(reward.model, s, a, n).numpy()
    np.testing.assert_allclose(scored.intrinsic_reward, expected, rtol=1e-5, atol=1e-7)
    assert scored.reward_kind == "elden" and (scored.intrinsic_reward > 0).any()


def test_curiosity_reads_the_elden_ensembles_prediction_error(thawing) -> None:
    worker, batches = thawing
    core = learner(thawing)
    reward = IntrinsicRewardCore(IntrinsicRewardConfig(method="elden", reward="curiosity"), worker.spec)
    reward.load_weights(core.weights())
    batch = batches[1]
    s, a, n = (torch.from_numpy(x) for x in (batch.state, batch.action, batch.next_state))
    np.testing.assert_allclose(reward.score(batch).intrinsic_reward, reward.model.prediction_nll(s, a, n).numpy(),
                               rtol=1e-5)
    with pytest.raises(ValueError, match="serves elden, curiosity"):
        IntrinsicRewardCore(IntrinsicRewardConfig(method="elden", reward="preddiff"), worker.spec)


def test_the_run_accepts_elden_rewards_only_with_the_elden_method() -> None:
    ok = resolve(build_config(RunConfig, router_port=7447, env="thawing", method="elden", collector="ppo",
                              intrinsic="elden"))
    assert ok.method == "elden"
    with pytest.raises(ValueError, match="method 'cdl' serves preddiff, curiosity"):
        resolve(build_config(RunConfig, router_port=7447, env="thawing", collector="ppo", intrinsic="elden"))


def test_an_elden_run_on_thawing_publishes_scored_local_graphs(tmp_path) -> None:
    cfg = build_config(RunConfig, method="elden", env="thawing", task="thaw-fish", run_dir=str(tmp_path),
                       run_id="el", learner_publish_every_s=0.5, evaluator_min_interval_s=0.5,
                       evaluator_local_samples=64, worker_max_steps_per_second=2000, progress=False, **TINY)
    stack = InProcessStack(cfg, config_overrides={"dynamics-learner": {"warmup_steps": 100},
                                                  "graph-evaluator": {"min_heldout": 30}})
    reports: list[LocalGraphReport] = []
    stack.transport().subscribe(topics.local("el", "elden"),
                                lambda _, payload: reports.append(decode(payload, LocalGraphReport)))
    stack.start()
    try:
        deadline = time.monotonic() + 45
        while time.monotonic() < deadline and len(reports) < 2:
            time.sleep(0.2)
    finally:
        stack.stop()
    assert len(reports) >= 2, "no local-graph report from the ELDEN run"
    last = reports[-1]
    assert last.kind == "elden" and last.estimator == "jacobian" and last.threshold == pytest.approx(3e-4)
    assert last.scores.shape[1:] == (21, 22) and last.updates > 0
    assert {"roc_auc", "pr_auc", "best_f1"} <= set(last.metrics)
