"""SkiLD in the services, without the bus: the env-worker's SkiLD actor and the policy-learner's SkiLD
core exchange real (encoded, decoded) Weights and SkillBatches; the budget switches the phase."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from causal.skild_agent import SkillLearnerConfig
from causal.skild_policy import MODEL, SkildPolicyConfig
from proto.codec import ProtocolError, decode, encode
from proto.messages import InducedGraphs, SkillBatch, Weights
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.policy_learner.config import PolicyLearnerConfig
from services.policy_learner.skild import EpisodeCoverage, SkildLearnerCore, phase_for

torch.set_num_threads(1)


def test_phase_switch_is_driven_by_the_budget() -> None:
    assert [phase_for(n, 500) for n in (0, 499, 500, 10_000)] == ["pretrain", "pretrain", "task", "task"]
    assert phase_for(0, 0) == "task"


def _stack(tmp_path, budget: int, graphs: str = "true") -> tuple[EnvWorkerCore, SkildLearnerCore]:
    worker = EnvWorkerCore(EnvWorkerConfig(env="installing-printer", run_dir=str(tmp_path), skild=True,
                                           local_graphs=graphs == "true", batch_steps=64, seed=3))
    skill = SkillLearnerConfig(learning_starts=128, batch_size=32, hidden=32, selector_batch=8)
    learner = SkildLearnerCore(PolicyLearnerConfig(skild=True, skild_pretrain_steps=budget, skild_graphs=graphs,
                                                   skill=skill, rollout_batches=2, skill_rollout=2, seed=3,
                                                   skild_updates_per_env_step=0.25, publish_every_updates=8),
                               worker.spec)
    learner.agent.history.eligible_after = 5
    return worker, learner


def _hand_over(learner: SkildLearnerCore, worker: EnvWorkerCore) -> None:
    assert worker.apply_weights(decode(encode(learner.weights()), Weights))


def test_pretrain_then_task_through_real_messages(tmp_path) -> None:
    worker, learner = _stack(tmp_path, budget=256)
    assert worker.waiting
    _hand_over(learner, worker)
    assert not worker.waiting and worker.skild.phase == "pretrain"
    for _ in range(12):
        batch = decode(encode(worker.collect_skills()), SkillBatch)
        assert batch.phase == worker.skild.phase and batch.started[0] or batch.started.any()
        assert learner.ingest(batch) == ""
        while learner.ready:
            learner.train_step()
        if learner.maybe_switch() or learner.publish_due:
            _hand_over(learner, worker)
    progress = learner.progress()
    assert learner.phase == "task" and worker.skild.phase == "task"
    # the replay links each of the worker's steps to the next of its episode, across batches (hindsight's
    # later steps), and never across episodes
    f, size = learner.agent.replay.fields, learner.agent.replay.size
    linked = np.flatnonzero(f["successor"][:size] >= 0)
    assert len(linked) >= size - 1 - f["terminated"][:size].sum() - size // 100
    nxt = f["successor"][linked]
    np.testing.assert_array_equal(f["episode"][nxt], f["episode"][linked])
    np.testing.assert_array_equal(f["step"][nxt], f["step"][linked] + 1)
    assert learner.pretrain_steps >= 256 and learner.task_steps > 0
    assert learner.updates >= 0.25 * (256 - 128) and learner.task_updates >= 1
    assert progress["targets"] >= 1 and progress["coverage_episodes_pretrain"] >= 1
    frozen = {k: v.clone() for k, v in learner.agent.q.state_dict().items()}
    config = SkildPolicyConfig.from_json(learner.weights().config_json)
    assert config.phase == "task" and len(config.targets) == len(learner.agent.history.targets)
    for _ in range(4):  # the low level stays frozen in the task phase
        learner.ingest(decode(encode(worker.collect_skills()), SkillBatch))
        while learner.ready:
            learner.train_step()
    assert all(torch.equal(frozen[k], v) for k, v in learner.agent.q.state_dict().items())


def test_a_burst_that_spends_the_budget_at_once_still_gets_its_updates(tmp_path) -> None:
    """The whole pre-training budget arriving in one drain of the inbox (as on a loaded CI machine)
    must not switch before the budget's skill updates are done."""
    worker, learner = _stack(tmp_path, budget=256)
    _hand_over(learner, worker)
    for _ in range(5):  # 320 steps, past the budget, before any update
        assert learner.ingest(worker.collect_skills()) == ""
    owed = learner.owed_updates
    assert owed == 0.25 * 256 and learner.updates == 0
    assert not learner.maybe_switch() and learner.phase == "pretrain"
    while not learner.maybe_switch():
        assert learner.ready
        learner.train_step()
    assert learner.phase == "task" and learner.updates == owed and learner.owed_updates == 0


def test_batches_of_the_other_phase_are_dropped(tmp_path) -> None:
    worker, learner = _stack(tmp_path, budget=64)
    _hand_over(learner, worker)
    stale = worker.collect_skills()
    assert learner.ingest(stale) == "" and learner.maybe_switch()
    assert learner.ingest(stale) == "phase" and learner.dropped["phase"] == 1


def test_evaluator_graphs_are_joined_by_worker_and_seq(tmp_path) -> None:
    worker, learner = _stack(tmp_path, budget=10_000, graphs="evaluator")
    _hand_over(learner, worker)
    first, second = worker.collect_skills(), worker.collect_skills()
    d = worker.spec.num_factors
    eye = np.repeat(np.eye(d, d + 1, dtype=np.uint8)[None], 64, axis=0)
    assert learner.ingest(first) == "" and learner.pretrain_steps == 0 and learner.waiting
    graphs = InducedGraphs("skild", first.transitions.worker_id, first.transitions.seq, 1, eye)
    assert learner.ingest(decode(encode(graphs), InducedGraphs)) == "" and learner.pretrain_steps == 64
    early = InducedGraphs("skild", second.transitions.worker_id, second.transitions.seq, 1, eye)
    assert learner.ingest(early) == "" and learner.ingest(second) == "" and learner.pretrain_steps == 128
    with pytest.raises(ProtocolError):
        learner.ingest(InducedGraphs("skild", "w0", 99, 1, np.zeros((64, d, d), np.uint8)))


def test_true_graphs_are_required_in_the_ablation(tmp_path) -> None:
    worker, learner = _stack(tmp_path, budget=10_000)
    _hand_over(learner, worker)
    batch = worker.collect_skills()
    bare = dataclasses.replace(batch, transitions=dataclasses.replace(batch.transitions, local_graph=None))
    with pytest.raises(ProtocolError):
        learner.ingest(bare)


def test_checkpoint_resumes_both_phases(tmp_path) -> None:
    worker, learner = _stack(tmp_path, budget=256)
    _hand_over(learner, worker)
    for _ in range(6):
        learner.ingest(worker.collect_skills())
        while learner.ready:
            learner.train_step()
    assert learner.maybe_switch()
    learner.checkpoint(tmp_path / "ckpt.pt")
    _, resumed = _stack(tmp_path, budget=256)
    assert resumed.restore(tmp_path / "ckpt.pt")
    assert resumed.phase == "task" and resumed.pretrain_steps == learner.pretrain_steps
    assert resumed.agent.history.targets == learner.agent.history.targets
    assert resumed.agent.replay.size == learner.agent.replay.size
    assert resumed.coverage.episodes == learner.coverage.episodes
    assert all(torch.equal(a, b) for a, b in zip(resumed.agent.q.state_dict().values(),
                                                 learner.agent.q.state_dict().values()))
    assert resumed.weights().version == learner.version + 1


def test_a_resumed_learner_links_the_worker_s_next_steps_to_those_it_saved(tmp_path) -> None:
    worker, learner = _stack(tmp_path, budget=10_000)
    _hand_over(learner, worker)
    for _ in range(2):
        learner.ingest(worker.collect_skills())
    learner.checkpoint(tmp_path / "ckpt.pt")
    _, resumed = _stack(tmp_path, budget=10_000)
    assert resumed.restore(tmp_path / "ckpt.pt")
    replay = resumed.agent.replay
    last = replay.size - 1
    batch = worker.collect_skills()
    resumed.ingest(batch)
    continues = batch.transitions.episode_id[0] == replay.fields["episode"][last] \
        and batch.transitions.step[0] == replay.fields["step"][last] + 1
    assert continues  # 2 x 64 steps of a 150-step episode: the third batch goes on with it
    assert replay.fields["successor"][last] == last + 1


def test_coverage_counts_each_episode_once() -> None:
    cov = EpisodeCoverage(2)
    row = np.zeros((3, 2, 3), bool)
    row[:, 1, [0, 1]] = True  # "a, b -> b" on every step
    cov.add("pretrain", "w0", np.array([0, 0, 1]), row, np.array([False, True, False]))
    cov.add("pretrain", "w0", np.array([1]), np.zeros((1, 2, 3), bool), np.array([True]))
    assert cov.episodes["pretrain"] == 2
    assert cov.named("pretrain", ("a", "b")) == {"a, b -> b": 1.0}


def test_weights_model_and_config_round_trip() -> None:
    cfg = SkildPolicyConfig("task", (3, 4), 2, 5, 4, 16, 8, 20, 0.1, ((1, 3),))
    assert SkildPolicyConfig.from_json(cfg.to_json()) == cfg and cfg.options == 4
    with pytest.raises(ValueError):
        SkildPolicyConfig.from_json('{"model": "policy"}')
    assert MODEL == "skild-policy"
