"""PPO over skills (the chapter's collection policy on manipulation): the learner learns which skill
pays, workers run the skill the published policy picks and mark its decisions in the batches."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from envs.skills import OPTION_NAMES
from proto.codec import decode, encode
from proto.fits import check_fits
from proto.messages import EnvSpec, TransitionBatch
from services.runtime.config import build_config
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.env_worker.service import option_counts
from services.policy_learner.config import PolicyLearnerConfig
from services.policy_learner.core import PolicyLearnerCore
from causal.rl.policy_weights import agent_from_config_json, import_policy, policy_options

PAYS = OPTION_NAMES.index("grasp:unm")


def _spec() -> EnvSpec:
    return EnvSpec(env_id="manipulation", factor_names=("p",), factor_kinds=("continuous",), factor_sizes=(2,),
                   factor_objects=("o",), factor_locs=(0.0,), factor_scales=(1.0,), action_kind="continuous",
                   action_size=4, episode_length=1000)


def _skill_batches(weights, seq: int, rng: np.random.Generator, decisions: int = 8, steps_per_skill: int = 3):
    """Steps of skills picked by the published policy; every step of the paying skill earns 1."""
    agent = agent_from_config_json(weights.config_json, seed=seq, obs_dim=2)
    import_policy(agent, weights.tensors)
    obs = rng.normal(size=(decisions, 2)).astype(np.float32)
    picked = [int(agent.act(o)) for o in obs]
    t = decisions * steps_per_skill
    state = np.repeat(obs, steps_per_skill, axis=0)
    option = np.full(t, -1, np.int32)
    option[::steps_per_skill] = picked
    reward = np.repeat([1.0 if p == PAYS else 0.0 for p in picked], steps_per_skill).astype(np.float32)
    return TransitionBatch(worker_id="w0", seq=seq, policy_version=weights.version, state=state,
                           action=np.zeros((t, 4), np.float32), reward=reward, next_state=state,
                           terminated=np.zeros(t, bool), truncated=np.zeros(t, bool),
                           episode_id=np.zeros(t, np.int64), step=np.arange(t, dtype=np.int32), option=option)


def test_ppo_over_skills_learns_to_pick_the_skill_that_pays() -> None:
    cfg = PolicyLearnerConfig(skills=True, skill_rollout=8, rollout_batches=2, hidden=16, minibatch_size=16,
                              epochs=4, lr=3e-3, gamma=0.5)
    core = PolicyLearnerCore(cfg, _spec())
    assert policy_options(core.weights().config_json) == OPTION_NAMES
    rng = np.random.default_rng(0)
    probe = torch.from_numpy(rng.normal(size=(256, 2)).astype(np.float32))
    before = core.agent.net.distribution(probe).probs[:, PAYS].mean().item()
    weights, seq = core.weights(), 0
    while core.updates < 40:
        assert core.ingest(_skill_batches(weights, seq, rng)).dropped == ""
        seq += 1
        if core.ready:
            core.train_step()
            weights = core.weights()
    after = core.agent.net.distribution(probe).probs[:, PAYS].mean().item()
    assert before == pytest.approx(1 / len(OPTION_NAMES), abs=0.02)
    assert after > 0.6, after
    assert core.progress()["decisions"] == 8 * seq - 1  # the last skill is still running


def test_minibatches_over_skills_are_one_column_of_decisions() -> None:
    assert PolicyLearnerConfig(skills=True).ppo().minibatch_size == PolicyLearnerConfig().skill_rollout == 8
    assert PolicyLearnerConfig().ppo().minibatch_size == 64  # motor actions: unchanged


def test_sac_over_skills_is_refused() -> None:
    with pytest.raises(ValueError, match="PPO"):
        PolicyLearnerConfig(algo="sac", skills=True)


def test_manipulation_worker_runs_the_skills_the_published_policy_picks() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="manipulation", batch_steps=128, follow_policy=True))
    uniform = worker.collect()
    assert uniform.policy_version == 0 and uniform.option[0] >= 0  # the Uniform skills mark decisions too
    assert set(option_counts(uniform, OPTION_NAMES)) <= {(name, "uniform") for name in OPTION_NAMES}
    learner = PolicyLearnerCore(PolicyLearnerConfig(skills=True, skill_rollout=2, rollout_batches=1), worker.spec)
    last = [m for m in learner.agent.net.actor.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.bias[PAYS] = 30.0  # a policy that always grasps the unmovable cube
    assert worker.apply_weights(decode(encode(learner.weights())))
    batches = [worker.collect() for _ in range(2)]  # 128 + 256 steps: crosses the 250-step episode end
    for batch in batches:
        check_fits(worker.spec, batch)
        assert decode(encode(batch)).option.tolist() == batch.option.tolist()
    picked = np.concatenate([b.option for b in batches])
    assert batches[0].policy_version == 1 and set(picked[picked >= 0]) == {PAYS}
    end = np.flatnonzero(np.concatenate([b.truncated for b in batches]))
    assert end.size == 1 and picked[end[0] + 1] == PAYS  # a new episode starts with a fresh decision
    assert option_counts(batches[1], OPTION_NAMES) == {("grasp:unm", "learned"): int((batches[1].option >= 0).sum())}
    for batch in batches:
        assert learner.ingest(batch).dropped == ""
    assert learner.stitcher.decisions >= 3 and learner.ready
    assert np.isfinite(learner.train_step()["policy_loss"])
    other = learner.weights()
    renamed = dataclasses.replace(other, version=other.version + 1,
                                  config_json=other.config_json.replace('"grasp:unm"', '"grasp:lid"'))
    with pytest.raises(ValueError, match="grasp:lid"):
        worker.apply_weights(renamed)  # another env's skills: refused, the running policy stays
    assert worker.actor.version == 1


def test_a_worker_without_skills_rejects_a_policy_over_skills() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=64, follow_policy=True))
    with pytest.raises(ValueError, match="has no skills"):
        PolicyLearnerCore(PolicyLearnerConfig(skills=True), worker.spec)
    learner = PolicyLearnerCore(PolicyLearnerConfig(skills=True), dataclasses.replace(worker.spec, env_id="manipulation"))
    with pytest.raises(ValueError, match="skills"):
        worker.apply_weights(learner.weights())
    assert worker.policy is worker.random_policy
