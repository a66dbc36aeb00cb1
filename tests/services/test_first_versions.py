"""First versions (issue 20): a consumer does not take an arbitrary first version from a publisher it has
not heard from. The first one is bounded by a version known published without the publisher's word: the
consumer's checkpoint, or what the supervisor read for it (the learner's record of its publications, on
disk). Real learner, evaluator, intrinsic-reward and env-worker cores; real checkpoints in a temporary
directory; a real supervisor object (no router) for the reports it takes and the versions it hands out."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from proto import topics
from proto.codec import ProtocolError, encode
from proto.messages import GraphReport, ServiceStats
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore, PolicyActor
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.intrinsic_reward.core import IntrinsicRewardCore
from services.runtime.accept import UNKNOWN, VersionGate
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.supervisor import Supervisor

SMALL = dict(cdl_feature_hidden=8, cdl_feature_dim=8, cdl_predictor_hidden=8, cdl_batch_size=16, warmup_steps=16)
FORGED = 2**62


@pytest.fixture(scope="module")
def worker() -> EnvWorkerCore:
    return EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3, batch_steps=64, seed=5))


def new_learner(worker: EnvWorkerCore) -> DynamicsLearnerCore:
    core = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **SMALL, seed=5), worker.spec)
    core.ingest(worker.collect())
    core.train_step()
    return core


def new_evaluator(worker: EnvWorkerCore, known: int = 0) -> GraphEvaluatorCore:
    cfg = build_config(GraphEvaluatorConfig, min_heldout=1, heldout_capacity=100, known_version=known)
    return GraphEvaluatorCore(cfg, worker.spec)


def test_a_first_version_is_bounded_by_a_version_known_published() -> None:
    gate = VersionGate(max_step=10)
    with pytest.raises(ProtocolError, match="jumps more than 10 past the 0 known published"):
        gate.take("w", FORGED)
    assert "w" not in gate.last and gate.take("w", 10)
    gate = VersionGate(max_step=10, known=100)
    with pytest.raises(ProtocolError, match="past the 100 known published"):
        gate.take("a", 111)
    assert gate.take("a", 110)
    gate.know(200)  # a checkpoint's version raises the bound of publishers not heard from yet
    gate.know(150)  # and never lowers it
    assert gate.known == 200 and gate.take("b", 210) and gate.take("a", 120)
    with pytest.raises(ProtocolError, match=r"version 7 was never published \(the highest published is 6\)"):
        gate.take("c", 7, ceiling=6)
    with pytest.raises(ValueError):
        VersionGate(known=-2)


def test_with_nothing_known_a_first_version_is_taken_and_the_steps_after_it_bounded() -> None:
    """compose and Kubernetes (no supervisor sets known_version): a consumer restarted without a
    checkpoint late in a run must take the learner's versions, not refuse them for good."""
    gate = VersionGate(max_step=10, known=UNKNOWN)
    assert gate.take("w", 50_000) and not gate.take("w", 50_000) and gate.take("w", 50_010)
    with pytest.raises(ProtocolError, match="jumps more than 10 past the last accepted 50010"):
        gate.take("w", FORGED)
    gate.know(60_000)  # a checkpoint's version bounds the publishers not heard from yet again
    with pytest.raises(ProtocolError, match="past the 60000 known published"):
        gate.take("v", FORGED)
    assert build_config(GraphEvaluatorConfig).known_version == UNKNOWN


def test_forged_first_weights_are_refused_and_the_real_first_ones_taken(worker: EnvWorkerCore) -> None:
    """Issue 20's forged weights (version 2**62, zeroed tensors) reaching a fresh consumer before any
    real message: refused; the learner's real first weights are then taken."""
    learner = new_learner(worker)
    real = learner.weights()
    forged = dataclasses.replace(real, version=FORGED, tensors={k: np.zeros_like(v) for k, v in real.tensors.items()})
    evaluator = new_evaluator(worker)
    scorer = IntrinsicRewardCore(build_config(IntrinsicRewardConfig, known_version=0), worker.spec)  # as a fresh local run sets it
    for consumer in (evaluator, scorer):
        with pytest.raises(ProtocolError, match="first version"):
            consumer.load_weights(forged)
        consumer.load_weights(real)
    assert evaluator.weights is real and evaluator.versions.last["cdl"] == real.version
    assert scorer.weights_version == real.version


def test_forged_first_policy_weights_are_refused_by_an_env_worker(worker: EnvWorkerCore) -> None:
    from services.policy_learner.config import PolicyLearnerConfig
    from services.policy_learner.core import PolicyLearnerCore

    real = PolicyLearnerCore(PolicyLearnerConfig(algo="ppo", hidden=16), worker.spec).weights()
    actor = PolicyActor(worker.spec.state_dim, 0, worker.env.action_space)
    with pytest.raises(ProtocolError, match="first version"):
        actor.load(dataclasses.replace(real, version=FORGED))
    assert actor.agent is None and actor.load(real) and actor.version == real.version
    # A worker started late in a long run: the supervisor tells it the policy-learner's last version.
    late = PolicyActor(worker.spec.state_dim, 0, worker.env.action_space, known_version=50_000)
    assert late.load(dataclasses.replace(real, version=50_001)) and late.version == 50_001


def test_an_evaluator_restarted_from_its_checkpoint_bounds_first_versions_by_it(worker: EnvWorkerCore,
                                                                               tmp_path: Path) -> None:
    """A long run: the learner is past version 20,000. An evaluator restarted from its checkpoint takes the
    learner's next weights as its first (they are within the bound of the version it had evaluated), and
    still refuses a forged 2**62."""
    learner = new_learner(worker)
    learner.version = 20_000
    evaluator = new_evaluator(worker)
    evaluator.versions.know(learner.version)  # as the supervisor's known_version would have
    while evaluator.heldout.size < 1:  # a batch's episodes are held out at random (seeded)
        evaluator.ingest(worker.collect())
    evaluator.load_weights(learner.weights())
    assert evaluator.due
    evaluator.evaluate()
    evaluator.checkpoint(tmp_path / "graph-evaluator-0.pt")
    restarted = new_evaluator(worker)
    assert restarted.restore(tmp_path / "graph-evaluator-0.pt") and restarted.versions.known == 20_001
    real = learner.weights()
    with pytest.raises(ProtocolError, match="first version"):
        restarted.load_weights(dataclasses.replace(real, version=FORGED))
    restarted.load_weights(real)
    assert restarted.weights is real and restarted.due  # version 20,002 is newer than the evaluated one
    without = new_evaluator(worker)  # no checkpoint, nothing known: the bound is from 0
    with pytest.raises(ProtocolError, match="first version"):
        without.load_weights(real)


def test_a_learner_restarted_from_its_checkpoint_continues_above_every_version_it_published(
        worker: EnvWorkerCore, tmp_path: Path) -> None:
    """Killed after publishing versions its checkpoint does not know: it resumes above them, so consumers
    that took them take its next ones, and a fresh consumer told the learner's record takes them too."""
    ckpt = tmp_path / "dynamics-learner-0.pt"
    learner = new_learner(worker)
    learner.checkpoint(ckpt)
    evaluator = new_evaluator(worker)
    for _ in range(3):
        weights = learner.weights()
        learner.record_version(ckpt)
        evaluator.load_weights(weights)
    resumed = new_learner(worker)
    assert resumed.restore(ckpt) and resumed.version == weights.version
    after = resumed.weights()
    assert after.version == weights.version + 1
    evaluator.load_weights(after)
    assert evaluator.weights is after
    fresh = new_evaluator(worker, known=weights.version)
    fresh.load_weights(after)
    assert fresh.weights is after


def supervisor(tmp_path: Path) -> Supervisor:
    return Supervisor(build_config(RunConfig, router_port=7447, run_dir=str(tmp_path), run_id="run", progress=False))


def report(worker: EnvWorkerCore, version: int) -> bytes:
    n = worker.spec.num_factors
    return encode(GraphReport(kind="cdl", weights_version=version, env_steps=0, updates=0,
                              factor_names=worker.spec.factor_names, cmi=np.zeros((n, n + 1), np.float32),
                              adjacency=np.zeros((n, n + 1), np.uint8), threshold=0.02, controllable=(),
                              action_relevant=(), action_irrelevant=(), metrics={}, timestamp=0.0))


def test_the_supervisor_takes_no_report_of_weights_never_published(worker: EnvWorkerCore, tmp_path: Path) -> None:
    """The learner's record (written before each publication) is the ceiling: a forged report above it
    never enters the run's history, the first real one does; processes it starts are told it."""
    sup = supervisor(tmp_path)
    key = topics.graph("run", "cdl")
    sup._on_graph(key, report(worker, 1))
    assert sup.history == [] and sup.published_version() == 0
    learner = new_learner(worker)
    learner.version = 12
    learner.record_version(tmp_path / "checkpoints" / "dynamics-learner-0.pt")
    assert sup.published_version() == 12 and sup.known_version(policy=False) == 12
    sup._on_graph(key, report(worker, FORGED))
    sup._on_graph(key, report(worker, 13))
    assert sup.history == []
    sup._on_graph(key, report(worker, 12))
    assert [h["updates"] for h in sup.history] == [0] and sup.last_report.weights_version == 12


def test_the_supervisor_tells_a_worker_the_policy_learners_last_version(tmp_path: Path) -> None:
    sup = supervisor(tmp_path)
    assert sup.known_version(policy=True) == 0
    sup.started.add("policy-learner")
    beat = ServiceStats(service="policy-learner", instance="0", values={"policy_version": 321.0}, timestamp=0.0)
    sup._on_stats(topics.stats("run", "policy-learner", "0"), encode(beat))
    assert sup.known_version(policy=True) == 321
    env = sup.process("env-worker-0", "services.env_worker", build_config(EnvWorkerConfig)).refresh()
    assert env == {"CAUSEWAY_KNOWN_VERSION": "321"}


def test_a_stats_beat_counts_only_under_its_own_key(tmp_path: Path) -> None:
    """With identities per instance the router lets only worker 1 publish on stats/env-worker/1; a beat that
    names worker 1 on another key (worker 0's, which worker 0 may use) is not counted as worker 1's."""
    sup = supervisor(tmp_path)
    sup.started |= {"env-worker-0", "env-worker-1"}
    beat = ServiceStats(service="env-worker", instance="1", values={"env_steps": 1e6}, timestamp=0.0)
    sup._on_stats(topics.stats("run", "env-worker", "0"), encode(beat))
    assert sup.progress.env_steps() == 0 and ("env-worker", "1") in sup.strangers
    own = ServiceStats(service="env-worker", instance="1", values={"env_steps": 64.0}, timestamp=0.0)
    sup._on_stats(topics.stats("run", "env-worker", "1"), encode(own))
    assert sup.progress.env_steps() == 64


def test_a_workers_message_must_name_the_worker_of_its_key(worker: EnvWorkerCore) -> None:
    """The router pins worker i to ``transitions/w<i>``; the consumers' inboxes pin the batch's own
    ``worker_id`` to that key (transitions, and the scored batches that wrap them)."""
    from proto.messages import ScoredBatch, TransitionBatch
    from services.runtime.metrics import ServiceMetrics
    from services.runtime.shell import Inbox

    metrics = ServiceMetrics("test", "0")
    inbox = Inbox("transitions", (TransitionBatch, ScoredBatch), maxsize=8, metrics=metrics)
    batch = worker.collect()
    scored = ScoredBatch(transitions=batch, intrinsic_reward=np.zeros(len(batch), np.float32), reward_kind="preddiff",
                         weights_version=0)
    other = "w" + str(int(batch.worker_id[1:]) + 1)
    for key in (topics.transitions("run", other), topics.scored("run", other)):
        inbox.on_payload(key, encode(batch if "transitions" in key else scored))
    assert inbox.drain() == [] and metrics.rejected_count == 2
    inbox.on_payload(topics.transitions("run", batch.worker_id), encode(batch))
    inbox.on_payload(topics.scored("run", batch.worker_id), encode(scored))
    assert [k for k, _ in inbox.drain()] == [topics.transitions("run", batch.worker_id),
                                            topics.scored("run", batch.worker_id)]


def test_scaled_workers_take_free_identities_below_the_limit(tmp_path: Path) -> None:
    """Indices are bus identities drawn at the start (--max-workers of them): a scaled-up worker takes the
    lowest one no running or still-stopping worker holds, never one beyond the limit."""
    import subprocess
    import sys

    sup = Supervisor(build_config(RunConfig, router_port=7447, run_dir=str(tmp_path), run_id="run", progress=False,
                                  max_workers=3))
    sup.add_worker = lambda index: sup.process(f"env-worker-{index}", "services.env_worker", build_config(EnvWorkerConfig))
    sup._write_process_table = lambda: None
    sup.scale_workers(3)
    assert sup.worker_indices() == [0, 1, 2] and sup.free_worker_index() is None
    stopping = sup.processes["env-worker-1"]
    stopping.process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        stopping.terminate = lambda: None  # still stopping: it keeps its identity
        sup.scale_workers(1)
        assert sup.worker_indices() == [0] and sup.free_worker_index() == 2
        sup.scale_workers(3)  # only index 2 is free until worker 1 has exited
        assert sup.worker_indices() == [0, 2]
    finally:
        stopping.process.kill()
        stopping.process.wait()
    assert sup.free_worker_index() == 1
    sup.scale_workers(3)
    assert sup.worker_indices() == [0, 1, 2]
