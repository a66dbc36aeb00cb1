"""Chapter 4's distractors: the gymnasium contract, the values the text gives them, and a ground truth
checked by interventions on the simulator (each distractor has exactly the parents it should, and
is the parent of nothing, the reward included)."""
from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from envs.chemical_distractors import ChemicalDistractorsEnv
from envs.chemical_match import ChemicalMatchEnv
from envs.distractors import Distractors, is_distractor, parse_distractors
from envs.registry import EnvOptions, env_entry
from envs.task_truth import parents_through_step
from proto.codec import decode, encode
from proto.messages import EnvSpec

SMALL = dict(graph="full", num_objects=3, distractors="3,2")


def test_check_env_passes_without_warnings_and_gym_make_builds_it() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(ChemicalDistractorsEnv(**SMALL), skip_render_check=True)
    env = gym.make("causeway/ChemicalDistractors-v0", num_objects=2, distractors="1,1")
    assert env.reset(seed=0)[0].shape == (2 * 4 + 2,)


def test_distractor_option_is_parsed_and_checked() -> None:
    assert parse_distractors("20,20") == (20, 20) and parse_distractors(" 0 ,5") == (0, 5)
    for bad in ("20", "a,b", "-1,2", "1,2,3", "300,0"):
        with pytest.raises(ValueError):
            EnvOptions(distractors=bad)
    entry = env_entry("chemical-distractors")
    assert entry.kwargs(EnvOptions(distractors="2,3", num_objects=4))["distractors"] == "2,3"
    assert "distractors" not in env_entry("chemical").kwargs(EnvOptions())


def test_values_projections_of_the_action_and_uniform_noise() -> None:
    env = ChemicalDistractorsEnv(**SMALL)
    obs, _ = env.reset(seed=1)
    n = 12
    np.testing.assert_array_equal(obs[n : n + 3], 0.0)  # controllable ones start at 0
    draws = []
    for t in range(200):
        action = t % env.action_space.n
        obs, reward, *_ = env.step(action)
        np.testing.assert_allclose(obs[n : n + 3], env.distractors.projection[:, action], rtol=1e-6)
        draws.append(obs[n + 3 :])
        assert reward == pytest.approx(env.match_fraction(obs))
    draws = np.concatenate(draws)
    assert draws.min() >= -1 and draws.max() <= 1 and abs(draws.mean()) < 0.1
    assert draws.std() == pytest.approx(3 ** -0.5, abs=0.05)  # U(-1, 1)
    assert np.abs(env.distractors.projection).max() <= 1


def test_continuous_projections_stay_in_range() -> None:
    d = Distractors(5, 0, "continuous", 4, seed=3)
    rng = np.random.default_rng(0)
    values = np.stack([d.step(rng.uniform(-1, 1, 4), rng) for _ in range(500)])
    assert np.abs(values).max() <= 1 + 1e-9 and values.std() > 0.1


def test_spec_truth_names_and_reward_parents() -> None:
    env = ChemicalDistractorsEnv(**SMALL)
    spec = env.env_spec()
    assert spec.env_id == "chemical-distractors" and spec.num_factors == 17 and spec.state_dim == 17
    assert spec.factor_names[12:] == ("cd.0", "cd.1", "cd.2", "ud.0", "ud.1")
    assert [is_distractor(name) for name in spec.factor_names].count(True) == 5
    assert decode(encode(spec), EnvSpec).reward_parents.tolist() == spec.reward_parents.tolist()
    truth = spec.global_graph
    np.testing.assert_array_equal(truth[:12, :12], ChemicalMatchEnv(graph="full", num_objects=3).global_graph[:, :12])
    assert truth[12:15, -1].all() and not truth[15:, -1].any()          # cd <- action, ud not
    assert (truth[12:, 12:17] == np.eye(5, dtype=np.uint8)).all()         # only their self-edges
    assert not truth[:12, 12:17].any() and not truth[12:, :12].any()      # no interaction
    colours, goals = [0, 3, 6], [9, 10, 11]
    expected = np.zeros(18, np.uint8)
    expected[[0, 3] + goals + [17]] = 1  # obj2's colour is overwritten by every action on the full graph
    np.testing.assert_array_equal(spec.reward_parents, expected)
    np.testing.assert_array_equal(parents_through_step(env.dependencies(), colours + goals), expected)
    assert parents_through_step(truth, colours + goals)[6] == 1  # the graph's assumed self-edge would say it is


def _next(env: ChemicalDistractorsEnv, state: np.ndarray, action: int, seed: int) -> tuple[np.ndarray, float]:
    env.reset(seed=seed)
    env.set_state(state)
    obs, reward, *_ = env.step(action)
    return obs, reward


def test_ground_truth_matches_interventions_on_the_simulator() -> None:
    """Change one factor (or the action) of a state, keep the random draws: the next factors (and the
    reward) that change are children of it. Every edge found must be in the truth, and every true
    edge of a distractor (row or column) must be found."""
    env = ChemicalDistractorsEnv(**SMALL)
    spec, rng = env.env_spec(), np.random.default_rng(0)
    d = spec.num_factors
    found, reward_found = np.eye(d, d + 1, dtype=np.uint8), np.zeros(d + 1, np.uint8)
    for trial in range(30):
        state, _ = env.reset(seed=100 + trial)
        state = env.sample_next_states(state[None], int(rng.integers(env.action_space.n)))[0]
        action = int(rng.integers(env.action_space.n))
        base, base_reward = _next(env, state, action, trial)
        for i in range(d + 1):
            changed, act = state.copy(), action
            if i == d:
                act = (action + 1 + int(rng.integers(env.action_space.n - 1))) % env.action_space.n
            elif spec.factor_kinds[i] == "categorical":
                changed[i] = (changed[i] + 1 + rng.integers(spec.factor_sizes[i] - 1)) % spec.factor_sizes[i]
            else:
                changed[i] += rng.uniform(0.5, 1.0)
            nxt, reward = _next(env, changed, act, trial)
            found[:, i] |= (nxt != base).astype(np.uint8)
            reward_found[i] |= np.uint8(reward != base_reward)
    distractors = slice(12, 17)
    assert (found <= spec.global_graph).all(), "an intervention found an edge the truth lacks"
    np.testing.assert_array_equal(found[distractors], spec.global_graph[distractors])
    np.testing.assert_array_equal(found[:, 12:17], spec.global_graph[:, 12:17])
    assert (reward_found <= spec.reward_parents).all() and not reward_found[12:17].any()
    np.testing.assert_array_equal(reward_found, spec.reward_parents)  # each true parent was seen to matter


def test_match_first_rewards_object_0_only_and_its_minimal_abstraction_is_two_factors() -> None:
    from causal.abstraction import cdl_abstraction, minimal_abstraction

    env = ChemicalDistractorsEnv(task="match-first", **SMALL)
    env.reset(seed=0)
    obs = env._observation()  # noqa: SLF001
    obs[:12] = [1, 0, 0, 2, 0, 0, 3, 0, 0, 1, 0, 0]  # obj0 matches its goal, obj1 and obj2 do not
    assert env.match_fraction(obs) == 1.0
    obs[9] = 4
    assert env.match_fraction(obs) == 0.0
    spec = env.env_spec()
    assert [spec.factor_names[i] for i in np.flatnonzero(spec.reward_parents[:-1])] == ["obj0.color", "obj0.goal_color"]
    kept = minimal_abstraction(spec.global_graph, spec.reward_parents).kept
    assert [spec.factor_names[j] for j in kept] == ["obj0.color", "obj0.goal_color"]
    assert len(cdl_abstraction(spec.global_graph).kept) == 3 + 3  # every colour and controllable distractor
    assert env_entry("chemical-distractors").kwargs(EnvOptions(task="match-first"))["task"] == "match-first"
    with pytest.raises(ValueError, match="task must be one of"):
        ChemicalDistractorsEnv(task="stack", **SMALL)


def test_out_of_distribution_values_are_the_in_distribution_episode_lifted_out_of_range() -> None:
    lo, hi = 1.0, 3.0
    plain = ChemicalDistractorsEnv(**SMALL)
    ood = ChemicalDistractorsEnv(**SMALL, distractor_ood=(lo, hi))
    assert ood.observation_space.high[12:].tolist() == [hi] * 5 and plain.observation_space.high[12:].tolist() == [1.0] * 5
    a, _ = plain.reset(seed=4)
    b, _ = ood.reset(seed=4)
    values, lifted = [], []
    for t in range(300):
        action = (7 * t) % plain.action_space.n
        np.testing.assert_array_equal(a[:12], b[:12])  # the task's factors are untouched
        values.append(a[12:]), lifted.append(b[12:])
        a, ra, *_ = plain.step(action)
        b, rb, *_ = ood.step(action)
        assert ra == rb
    values, lifted = np.concatenate(values), np.concatenate(lifted)
    assert np.abs(values).max() <= 1.0
    assert np.abs(lifted).min() >= lo - 1e-6 and np.abs(lifted).max() <= hi + 1e-6
    expected = np.where(values < 0, -1.0, 1.0) * (lo + (hi - lo) * np.abs(values))
    np.testing.assert_allclose(lifted, expected, rtol=1e-5, atol=1e-5)
    uncontrollable = lifted.reshape(-1, 5)[:, 3:].ravel()
    assert (uncontrollable > 0).mean() == pytest.approx(0.5, abs=0.08)  # both sides of the gap
    assert ood.config()["distractor_ood"] == [lo, hi] and "distractor_ood" not in plain.config()


def test_out_of_distribution_range_is_checked_and_in_distribution_behaviour_is_unchanged() -> None:
    for bad in ((0.5, 3.0), (3.0, 1.0)):
        with pytest.raises(ValueError):
            Distractors(2, 2, "categorical", 4, ood_range=bad)
    rng_a, rng_b = np.random.default_rng(9), np.random.default_rng(9)
    d = Distractors(2, 3, "categorical", 4, seed=1)
    assert d.bound == 1.0 and d.ood_range is None
    first = d.reset(rng_a)
    np.testing.assert_array_equal(first[:2], 0.0)
    np.testing.assert_array_equal(first[2:], np.random.default_rng(9).uniform(-1.0, 1.0, 3))
    rng_b.uniform(-1.0, 1.0, 3)  # the reset's draws
    np.testing.assert_array_equal(d.step(3, rng_a), np.append(d.projection[:, 3], rng_b.uniform(-1.0, 1.0, 3)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(ChemicalDistractorsEnv(**SMALL, distractor_ood=(1.0, 3.0)), skip_render_check=True)
