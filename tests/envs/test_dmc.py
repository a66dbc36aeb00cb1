"""The DeepMind Control Suite environments with chapter 4's distractors: factors named after the
model, the suite's dynamics and reward untouched, distractors with exactly their parents, the dense
truth and the reward's parents, seeded episodes, bad options refused before anything starts."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from causal.abstraction import minimal_abstraction
from envs.dmc import CheetahEnv, WalkerEnv
from envs.registry import check_options, env_entry, make_env, EnvOptions



@pytest.fixture(scope="module")
def walker() -> WalkerEnv:
    env = WalkerEnv()
    yield env
    env.close()


def test_walker_factors_spec_and_gymnasium_contract(walker: WalkerEnv) -> None:
    obs, _ = walker.reset(seed=0)
    assert obs.shape == (24 + 40,) and walker.factor_names[:2] == ("torso.xx", "torso.xz")
    assert walker.factor_names[14] == "height" and walker.factor_names[15:24] == tuple(
        f"{j}.vel" for j in ("rootz", "rootx", "rooty", "right_hip", "right_knee", "right_ankle",
                             "left_hip", "left_knee", "left_ankle"))
    spec = walker.env_spec()
    assert spec.env_id == "dmc-walker" and spec.action_kind == "continuous" and spec.action_size == 6
    assert spec.global_graph.shape == (64, 65) and spec.factor_objects[14] == "height"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(walker, skip_render_check=True)
    cheetah = make_env("dmc-cheetah", distractors="2,1", episode_length=10)
    assert cheetah.reset(seed=0)[0].shape == (17 + 3,) and cheetah.unwrapped.factor_names[0] == "rootz.pos"
    cheetah.close()


def test_the_suites_dynamics_and_reward_are_untouched(walker: WalkerEnv) -> None:
    from dm_control import suite

    obs, _ = walker.reset(seed=3)
    raw = suite.load("walker", "walk", task_kwargs={"random": 0})
    raw.reset()
    with raw.physics.reset_context():
        raw.physics.set_state(walker._env.physics.get_state())
    actions = np.random.default_rng(0).uniform(-1, 1, (20, 6))
    for a in actions:
        obs, reward, terminated, truncated, _ = walker.step(a)
        step = raw.step(a)
        scene = np.concatenate([np.atleast_1d(v) for v in step.observation.values()])
        np.testing.assert_allclose(obs[:24], scene, rtol=1e-5, atol=1e-6)
        assert reward == pytest.approx(step.reward) and not terminated and not truncated
        np.testing.assert_allclose(obs[24:44], walker.distractors.projection @ np.clip(a, -1, 1), rtol=1e-5)


def test_truth_distractor_parents_and_minimal_abstraction(walker: WalkerEnv) -> None:
    graph, n = walker.global_graph, 24
    assert graph[:n, :n].all() and graph[:n, -1].all() and not graph[:n, n:-1].any()
    assert graph[n:n + 20, -1].all() and not graph[n + 20:, -1].any()  # cd read the action, ud nothing
    np.testing.assert_array_equal(graph[n:, n:-1], np.eye(40, dtype=np.uint8))
    parents = walker.reward_parents
    assert parents[:n].all() and not parents[n:-1].any() and parents[-1]
    assert minimal_abstraction(graph, parents).kept == tuple(range(n))


def test_a_seed_fixes_the_episode() -> None:
    a, b = CheetahEnv(episode_length=5), CheetahEnv(episode_length=5)
    actions = np.random.default_rng(1).uniform(-1, 1, (5, 6))

    def rollout(env: CheetahEnv, seed: int) -> np.ndarray:
        rows = [env.reset(seed=seed)[0]]
        for k, action in enumerate(actions):
            obs, _, _, truncated, _ = env.step(action)
            rows.append(obs)
        assert truncated and k == 4  # episode_length steps
        return np.array(rows)

    first, again, other = rollout(a, 5), rollout(b, 5), rollout(a, 6)
    np.testing.assert_array_equal(first, again)
    assert not np.allclose(first[0, :17], other[0, :17]) and not np.allclose(first[:, -20:], other[:, -20:])


def test_bad_options_are_refused_before_anything_starts() -> None:
    with pytest.raises(ValueError, match=r"task must be one of \('walk', 'stand', 'run'\)"):
        check_options("dmc-walker", EnvOptions(task="swim"))
    with pytest.raises(ValueError, match=r"task must be one of \('run',\)"):
        CheetahEnv(task="walk")
    with pytest.raises(ValueError, match="episode_length must be >= 1"):
        WalkerEnv(episode_length=-1)
    entry = env_entry("dmc-walker")
    assert entry.kwargs(EnvOptions(task="stand", distractors="3,4")) == {"distractors": "3,4", "task": "stand"}
