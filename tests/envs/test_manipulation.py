"""The manipulation environment: gymnasium contract, seeding, layout, the ground truth's classes and
contact rules, the truth checked against the simulator by interventions, the lean controller against
robosuite's, and the factors that never vary.

Simulator steps cost ~10 ms here (~20 ms on robosuite's controller path), so every test takes few of
them and one environment is shared.
"""
from __future__ import annotations

import inspect
import json
import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from causal.abstraction import cdl_abstraction
from envs.manipulation import ManipulationEnv
from envs.manipulation_layout import (
    CONSTANT_FACTORS, EEF, FACTOR_NAMES, FIXED_HALF, GRP, MOV, MOV_BODY, RAND, RAND_BODY, ROBOT, STATIC, TABLE_TOP,
    UNM, UNM_BODY,
)
from envs.manipulation_truth import ACTION, global_graph, local_graph
from envs.skills import SkillPolicy, grasp


@pytest.fixture(scope="module")
def env() -> ManipulationEnv:
    env = ManipulationEnv()
    yield env
    env.close()


def _rollout(env: ManipulationEnv, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    observations, graphs = [], []
    for a in actions:
        obs, _, _, _, info = env.step(a)
        observations.append(obs)
        graphs.append(info["local_graph"])
    return np.array(observations), np.array(graphs)


def _toward(env: ManipulationEnv, obs: np.ndarray, target: np.ndarray, opening: float, steps: int) -> np.ndarray:
    for _ in range(steps):
        obs, *_ = env.step(np.r_[np.clip((target - obs[EEF]) / env.max_displacement, -1, 1), opening])
    return obs


def _names(indices: tuple[int, ...]) -> set[str]:
    return {FACTOR_NAMES[i] for i in indices}


def _objects(prefixes: tuple[str, ...]) -> set[str]:
    return {n for n in FACTOR_NAMES if n.split(".")[0] in prefixes}


# ---------------------------------------------------------------- gymnasium contract and seeding


def test_check_env_passes_without_warnings(env: ManipulationEnv) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, skip_render_check=True)


def test_reset_seed_makes_the_episode_reproducible(env: ManipulationEnv) -> None:
    actions = np.random.default_rng(0).uniform(env.action_space.low, env.action_space.high, (20, 4))
    first, _ = env.reset(seed=7)
    a_obs, a_graphs = _rollout(env, actions)
    fresh = ManipulationEnv()  # a fresh simulator, not only a fresh reset, gives the same episode
    again, _ = fresh.reset(seed=7)
    b_obs, b_graphs = _rollout(fresh, actions)
    other, _ = env.reset(seed=8)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(a_obs, b_obs)
    np.testing.assert_array_equal(a_graphs, b_graphs)
    assert not np.allclose(first[MOV], other[MOV])
    assert not np.allclose(first[RAND.start:], other[RAND.start:])


def test_layout_spaces_and_spec(env: ManipulationEnv) -> None:
    obs, info = env.reset(seed=0)
    assert obs.shape == (23,) and obs.dtype == np.float32 and info == {}
    assert env.factor_names[:5] == ("eef.x", "eef.y", "eef.z", "grp.0", "grp.1")
    assert env.factor_names[-3:] == ("mk3.x", "mk3.y", "mk3.z")
    assert env.action_space.shape == (4,) and env.action_space.low[3] == 0 and env.action_space.high[3] == 1
    assert np.allclose(obs[UNM][2], TABLE_TOP[2] + FIXED_HALF)
    spec = env.env_spec()
    assert spec.env_id == "manipulation" and spec.num_factors == spec.state_dim == 23
    assert spec.factor_kinds == ("continuous",) * 23 and spec.factor_sizes == (1,) * 23
    assert spec.factor_objects[:8] == ("eef",) * 3 + ("grp",) * 2 + ("mov",) * 3
    assert spec.action_kind == "continuous" and spec.action_size == spec.action_dim == 4
    assert spec.episode_length == 250 and spec.global_graph.shape == (23, 24)
    normalised = (obs - np.array(spec.factor_locs)) / np.array(spec.factor_scales)
    assert np.all(np.abs(normalised) < 3)
    config = json.loads(spec.config_json)
    assert set(config) == set(inspect.signature(ManipulationEnv).parameters) - {"render_mode"}
    with pytest.raises(ValueError):
        env.global_graph[0, 0] = 0


def test_episodes_truncate_after_episode_length() -> None:
    env = ManipulationEnv(episode_length=3)
    env.reset(seed=0)
    flags = [env.step(np.zeros(4, np.float32))[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]


def _grasp_then_wander(env: ManipulationEnv) -> list[tuple[np.ndarray, ...]]:
    """Observation, local graph and full physics state after each of 50 steps: grasp and lift ``mov``
    (contacts, a held cube), then random actions."""
    env.reset(seed=4)
    obs = env.intervene({"mov.x": 0.0, "mov.y": 0.0, "unm.x": 0.12, "unm.y": 0.15, "rand.x": -0.12, "rand.y": 0.15})
    skill, rng, steps = grasp("mov"), np.random.default_rng(0), []
    for _ in range(50):
        action = skill.act(obs)
        action = rng.uniform(env.action_space.low, env.action_space.high) if action is None else action
        obs, _, _, _, info = env.step(action)
        steps.append((obs, info["local_graph"], env.snapshot().physics))
    return steps


def test_lean_controller_is_robosuites_bit_for_bit(env: ManipulationEnv) -> None:
    reference = ManipulationEnv()
    reference.scene.robosuite_controller = True  # robosuite's own Robot.control every sub-step
    expected = _grasp_then_wander(reference)
    reference.close()
    steps = _grasp_then_wander(env)
    for got, want in zip(steps, expected):
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
    assert sum(graph[MOV, EEF].all() for _, graph, _ in steps) >= 10  # the cube was held


def test_constant_factors_never_change_and_the_others_do() -> None:
    env = ManipulationEnv(episode_length=60)
    policy = SkillPolicy(env.action_space, seed=0)
    episodes = []
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        steps, truncated = [obs], False
        while not truncated:
            obs, _, _, truncated, _ = env.step(policy.act(obs))
            steps.append(obs)
        episodes.append(np.array(steps))
    env.close()
    data = np.concatenate(episodes)
    constant = [FACTOR_NAMES.index(name) for name in env.constant_factors()]
    assert env.constant_factors() == CONSTANT_FACTORS
    assert np.all(data[:, constant] == data[0, constant])  # the same value in every step of every episode
    varying = np.ones(len(FACTOR_NAMES), dtype=bool)
    varying[constant] = False
    assert np.all(data[:, varying].std(axis=0) > 1e-3)
    assert global_graph()[:, constant].sum() - len(constant) == 16  # true edges no data can show


# ---------------------------------------------------------------- the ground truth


def test_global_graph_gives_the_chapters_classes() -> None:
    graph = global_graph()
    assert graph.shape == (23, 24) and graph.dtype == np.uint8
    assert np.all(np.diag(graph[:, :23]) == 1)
    classes = cdl_abstraction(graph)
    assert _names(classes.controllable) == _objects(("eef", "grp", "mov"))
    assert _names(classes.action_relevant) == _objects(("unm", "rand"))
    assert _names(classes.action_irrelevant) == _objects(("mk1", "mk2", "mk3"))


def test_global_graph_dimension_level_edges() -> None:
    graph = global_graph()
    for row in (EEF, GRP, MOV):
        assert np.all(graph[row, :14] == 1) and np.all(graph[row, ACTION] == 1)
        assert not graph[row, 14:23].any()  # nothing reads a marker
    for kinematic in range(8, 23):  # unm, rand, markers read only their own dimension
        assert np.flatnonzero(graph[kinematic]).tolist() == [kinematic]


def test_local_graphs_follow_contacts_and_union_to_the_global_graph() -> None:
    def touching(*pairs: tuple[int, int]) -> np.ndarray:
        c = np.zeros((5, 5), dtype=bool)
        for a, b in pairs:
            c[a, b] = c[b, a] = True
        return c

    free = local_graph(touching())
    assert free[EEF, ACTION].all() and free[GRP, ACTION].all() and not free[MOV, ACTION].any()
    assert not free[EEF, GRP].any() and not free[MOV, EEF].any()
    on_table = local_graph(touching((ROBOT, STATIC)))
    assert on_table[EEF, GRP].all() and not on_table[EEF, UNM].any()
    held = local_graph(touching((ROBOT, MOV_BODY)))
    assert held[MOV, ACTION].all() and held[MOV, EEF].all() and held[MOV, GRP].all() and held[EEF, MOV].all()
    pushed_alone = local_graph(touching((MOV_BODY, UNM_BODY)))  # e.g. rand shoved it there; no robot
    assert pushed_alone[MOV, UNM].all() and not pushed_alone[EEF, UNM].any()
    chain = local_graph(touching((ROBOT, MOV_BODY), (MOV_BODY, UNM_BODY)))
    assert chain[EEF, UNM].all() and chain[GRP, UNM].all() and chain[MOV, UNM].all()
    through_kinematic = local_graph(touching((ROBOT, RAND_BODY), (MOV_BODY, RAND_BODY)))
    assert not through_kinematic[MOV, EEF].any() and through_kinematic[MOV, RAND].all()
    rng = np.random.default_rng(0)
    union = np.zeros_like(free)
    for _ in range(300):
        c = np.triu(rng.random((5, 5)) < 0.3, 1)
        g = local_graph(c | c.T)
        assert np.all(g <= global_graph())
        union |= g
    np.testing.assert_array_equal(union, global_graph())


# ---------------------------------------------------------------- the truth against the simulator


def test_markers_change_nothing_else(env: ManipulationEnv) -> None:
    obs, _ = env.reset(seed=1)
    env.intervene({"mov.x": 0.0, "mov.y": 0.0, "unm.x": 0.12, "unm.y": 0.15, "rand.x": -0.12, "rand.y": 0.15})
    start = env.snapshot()
    actions = np.tile([0.8, 0.0, -1.0, 1.0], (12, 1)).astype(np.float32)  # sweep down over mov
    base, base_graphs = _rollout(env, actions)
    env.restore(start)
    env.intervene({"mk1.x": 0.0, "mk1.y": 0.0, "mk2.x": -0.05, "mk2.y": 0.0, "mk3.z": 0.85})
    moved, moved_graphs = _rollout(env, actions)
    np.testing.assert_array_equal(base[:, :14], moved[:, :14])  # eef, grp, mov, unm, rand untouched
    np.testing.assert_array_equal(base_graphs, moved_graphs)
    assert not np.allclose(base[:, 14:], moved[:, 14:])


def test_unm_blocks_the_end_effector_and_rand_is_not_moved(env: ManipulationEnv) -> None:
    obs, _ = env.reset(seed=2)
    obs = env.intervene({"mov.x": 0.1, "mov.y": -0.15, "unm.x": 0.1, "unm.y": 0.15, "rand.x": -0.1, "rand.y": 0.15})
    obs = _toward(env, obs, np.r_[0.0, 0.0, 0.9], 0.0, 12)
    start = env.snapshot()
    down = np.tile([0.0, 0.0, -1.0, 0.0], (10, 1)).astype(np.float32)
    free, _ = _rollout(env, down)
    env.restore(start)
    env.intervene({"unm.x": obs[0], "unm.y": obs[1]})  # unm under the gripper
    blocked, graphs = _rollout(env, down)
    np.testing.assert_array_equal(free[:, RAND], blocked[:, RAND])  # rand's walk ignores everything
    unm_top = TABLE_TOP[2] + 2 * FIXED_HALF
    assert free[-1, 2] < unm_top - 0.03 < unm_top < blocked[-1, 2]
    assert graphs[:, EEF, UNM].any() and not graphs[:, MOV, UNM].any()
    assert np.all(blocked[:, UNM][:, :2] == np.float32(obs[:2]))  # pushing unm does not move it
    env.restore(start)
    env.intervene({"rand.x": obs[0], "rand.y": obs[1]})
    walk = env.snapshot()
    pressed, graphs = _rollout(env, down)
    assert pressed[-1, 2] > unm_top and graphs[:, EEF, RAND].any()
    env.restore(walk)
    unpressed, _ = _rollout(env, np.tile([0.0, 0.0, 1.0, 1.0], (10, 1)).astype(np.float32))
    np.testing.assert_array_equal(pressed[:, RAND], unpressed[:, RAND])  # rand follows its walk only


def test_held_cube_moves_with_the_end_effector(env: ManipulationEnv) -> None:
    obs, _ = env.reset(seed=3)
    obs = env.intervene({"mov.x": 0.0, "mov.y": 0.0, "unm.x": 0.12, "unm.y": 0.15, "rand.x": -0.12, "rand.y": 0.15})
    obs = _toward(env, obs, obs[MOV] + [0, 0, 0.08], 1.0, 14)
    obs = _toward(env, obs, obs[MOV], 1.0, 8)
    obs = _toward(env, obs, obs[EEF], 0.0, 4)
    assert 0.015 < obs[GRP][0] < 0.025  # the fingers stop on the 4 cm cube
    lift = np.tile([0.0, 0.0, 1.0, 0.0], (4, 1)).astype(np.float32)
    carry = np.tile([0.0, 1.0, 0.0, 0.0], (4, 1)).astype(np.float32)
    held, graphs = _rollout(env, np.vstack([lift, carry]))
    assert held[-1, 7] > TABLE_TOP[2] + 0.06
    np.testing.assert_allclose(np.diff(held[:, MOV], axis=0), np.diff(held[:, EEF], axis=0), atol=0.004)
    assert graphs[:, MOV, ACTION].all() and graphs[:, MOV, EEF].all() and graphs[:, MOV, GRP].all()
    dropped, _ = _rollout(env, np.tile([0.0, 0.0, 0.0, 1.0], (5, 1)).astype(np.float32))  # open: it falls
    assert dropped[-1, 7] < TABLE_TOP[2] + 0.025
