"""policy-learner core: the policy-lag bound, PPO and SAC updates, versioned weights, the abstraction mask."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from proto.codec import decode, encode
from proto.messages import EnvSpec, GraphReport, ScoredBatch, TransitionBatch
from services.runtime.config import build_config
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.policy_learner.config import PolicyLearnerConfig
from services.policy_learner.core import PolicyLearnerCore
from causal.rl.policy_weights import agent_from_config_json

SMALL = dict(hidden=16, rollout_batches=2, minibatch_size=32, epochs=1)


def worker(**kwargs) -> EnvWorkerCore:
    return EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=64, follow_policy=True, **kwargs))


def relabel(batch: TransitionBatch, version: int) -> TransitionBatch:
    return dataclasses.replace(batch, policy_version=version)


def test_stale_future_and_random_policy_batches_are_dropped_and_counted() -> None:
    w = worker()
    core = PolicyLearnerCore(PolicyLearnerConfig(max_policy_lag=1, **SMALL), w.spec)
    random_batch = w.collect()
    assert random_batch.policy_version == 0
    assert core.ingest(random_batch).dropped == "random_policy"  # PPO cannot use the random warm-up
    assert w.apply_weights(decode(encode(core.weights())))
    assert core.ingest(random_batch).dropped == "random_policy"
    fresh = [w.collect() for _ in range(2)]
    assert all(b.policy_version == 1 for b in fresh)
    verdicts = [core.ingest(b) for b in fresh]
    assert [(v.lag, v.dropped) for v in verdicts] == [(0, ""), (0, "")]
    assert core.ready and core.env_steps == 128
    core.train_step()
    core.weights()  # v2
    assert core.ingest(fresh[0]).lag == 1 and len(core.pending) == 1  # lag 1 <= max_policy_lag: used
    core.weights()  # v3
    stale = core.ingest(fresh[1])
    assert (stale.lag, stale.dropped) == (2, "stale")
    assert core.ingest(relabel(fresh[1], 9)).dropped == "future"
    assert core.dropped == {"future": 1, "random_policy": 2, "stale": 1}
    assert core.lags == {"0": 3, "1": 2, "over": 1, "future": 1}  # every received batch, dropped or used
    assert core.progress()["lag_over"] == 1
    assert core.env_steps == 192 and len(core.pending) == 1


def test_ppo_updates_advance_versions_and_workers_act_with_them() -> None:
    w = worker()
    core = PolicyLearnerCore(PolicyLearnerConfig(**SMALL), w.spec)
    first = core.weights()
    w.apply_weights(first)
    for _ in range(2):
        core.ingest(w.collect())
    stats = core.train_step()
    assert np.isfinite(stats["policy_loss"]) and core.publish_due
    second = decode(encode(core.weights()))
    assert second.version == 2 and second.updates == 1
    assert any(not np.array_equal(first.tensors[k], second.tensors[k]) for k in first.tensors)
    assert w.apply_weights(second) and not w.apply_weights(first)
    batch = w.collect()
    assert batch.policy_version == 2 and w.policy is w.actor
    assert set(np.unique(batch.action)) <= set(range(w.spec.action_size))


def test_scored_batches_add_the_weighted_intrinsic_reward() -> None:
    w = worker()
    core = PolicyLearnerCore(PolicyLearnerConfig(intrinsic_coef=0.5, extrinsic_coef=0.0, **SMALL), w.spec)
    w.apply_weights(core.weights())
    batch = w.collect()
    intrinsic = np.linspace(-1, 1, len(batch)).astype(np.float32)
    core.ingest(ScoredBatch(transitions=batch, intrinsic_reward=intrinsic, reward_kind="preddiff", weights_version=1))
    torch.testing.assert_close(core.pending[0].rewards, torch.from_numpy(0.5 * intrinsic))


def _report(spec: EnvSpec, controllable: tuple[int, ...], relevant: tuple[int, ...], version: int) -> GraphReport:
    n = spec.num_factors
    rest = tuple(j for j in range(n) if j not in controllable + relevant)
    return GraphReport(kind="cdl", weights_version=version, env_steps=0, updates=0, factor_names=spec.factor_names,
                       cmi=np.zeros((n, n + 1), np.float32), adjacency=np.zeros((n, n + 1), np.uint8), threshold=0.02,
                       controllable=controllable, action_relevant=relevant, action_irrelevant=rest)


def test_abstraction_masks_the_policy_input_and_travels_with_the_weights() -> None:
    w = EnvWorkerCore(build_config(EnvWorkerConfig, env="chemical-match", num_objects=3, batch_steps=64))
    core = PolicyLearnerCore(PolicyLearnerConfig(**SMALL), w.spec)
    assert core.apply_graph(_report(w.spec, (0, 3), (6,), 1))
    assert core.kept_factors == (0, 3, 6, 9, 10, 11)  # + the provided goal colours
    assert not core.apply_graph(_report(w.spec, (0, 3), (6,), 2))  # unchanged
    mask = core.weights().tensors["input_mask.mask"]
    np.testing.assert_array_equal(np.flatnonzero(mask), [0, 3, 6, 9, 10, 11])
    dense = PolicyLearnerCore(PolicyLearnerConfig(abstraction=False, **SMALL), w.spec)
    assert not dense.apply_graph(_report(w.spec, (0,), (), 1))
    assert dense.weights().tensors["input_mask.mask"].all()


def _continuous_spec() -> EnvSpec:
    return EnvSpec(env_id="toy", factor_names=("p",), factor_kinds=("continuous",), factor_sizes=(2,),
                   factor_objects=("o",), factor_locs=(0.0,), factor_scales=(1.0,), action_kind="continuous",
                   action_size=2, episode_length=10)


def _toy_batch(version: int, steps: int = 64, seed: int = 0) -> TransitionBatch:
    rng = np.random.default_rng(seed)
    state = rng.normal(size=(steps, 2)).astype(np.float32)
    action = rng.uniform(-1, 1, (steps, 2)).astype(np.float32)
    return TransitionBatch(worker_id="w0", seq=0, policy_version=version, state=state, action=action,
                           reward=-np.square(action).sum(1).astype(np.float32), next_state=state + 0.1 * action,
                           terminated=np.zeros(steps, bool), truncated=np.zeros(steps, bool),
                           episode_id=np.zeros(steps, np.int64), step=np.arange(steps, dtype=np.int32))


@pytest.mark.parametrize("algo", ["sac", "ppo"])
def test_continuous_actions_behind_the_same_interface(algo: str) -> None:
    cfg = PolicyLearnerConfig(algo=algo, warmup_steps=64, batch_size=32, max_policy_lag=2, **SMALL)
    core = PolicyLearnerCore(cfg, _continuous_spec())
    published = core.weights()
    verdicts = [core.ingest(_toy_batch(v, seed=s)) for s, v in enumerate((0, 1, 1))]
    expected = ["", "", ""] if algo == "sac" else ["random_policy", "", ""]
    assert [v.dropped for v in verdicts] == expected and core.ready
    core.train_step()
    assert core.publish_due == (algo == "ppo")
    actor = agent_from_config_json(published.config_json, seed=0, obs_dim=2)
    action = actor.act(np.zeros(2, np.float32))
    assert action.shape == (2,) and np.all(np.abs(action) <= 1)
    with pytest.raises(ValueError, match="width"):
        agent_from_config_json(published.config_json, seed=0, obs_dim=3)


def test_checkpoint_resumes_the_version_sequence(tmp_path) -> None:
    w = worker()
    core = PolicyLearnerCore(PolicyLearnerConfig(**SMALL), w.spec)
    w.apply_weights(core.weights())
    for _ in range(2):
        core.ingest(w.collect())
    core.train_step()
    core.weights()
    core.checkpoint(tmp_path / "p.pt")
    again = PolicyLearnerCore(PolicyLearnerConfig(**SMALL), w.spec)
    assert again.restore(tmp_path / "p.pt") and (again.version, again.updates) == (2, 1)
    assert again.weights().version == 3
    assert again.ingest(w.collect()).dropped == "unknown_policy"  # v1's behaviour policy is gone


def test_hidden_factors_stay_out_of_the_policy_input_whatever_the_graph_says() -> None:
    spec = EnvSpec(env_id="toy", factor_names=("eef", "mk1", "mk2", "mov"), factor_kinds=("continuous",) * 4,
                   factor_sizes=(2, 1, 1, 3), factor_objects=("eef", "mk1", "mk2", "mov"), factor_locs=(0.0,) * 4,
                   factor_scales=(1.0,) * 4, action_kind="continuous", action_size=2, episode_length=10)
    core = PolicyLearnerCore(PolicyLearnerConfig(hide="mk, zz", **SMALL), spec)
    np.testing.assert_array_equal(core.weights().tensors["input_mask.mask"], [1, 1, 0, 0, 1, 1, 1])
    assert core.apply_graph(_report(spec, (0, 1), (2, 3), 1))  # a graph that (wrongly) keeps the markers
    assert core.kept_factors == (0, 3)
    np.testing.assert_array_equal(core.weights().tensors["input_mask.mask"], [1, 1, 0, 0, 1, 1, 1])
    plain = PolicyLearnerCore(PolicyLearnerConfig(**SMALL), spec)
    assert plain.weights().tensors["input_mask.mask"].all()
