"""Chapter 4's block environment: layout and spec, the distractors' exact parents (checked by
interventions on the simulator), the tasks' reward parents and minimal abstraction, Pick reached by a
scripted grasp and Stack's success detected, bad options refused, and seeded episodes reproducible.

Simulator steps cost ~20 ms here, so every test takes few of them and one environment is shared.
"""
from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from causal.abstraction import minimal_abstraction
from envs.block import PICK_HEIGHT, TASKS, BlockEnv, task_reward, task_reward_parents
from envs.distractors import Distractors
from envs.manipulation_layout import BLOCK, FIXED_HALF, MOV_HALF, TABLE_TOP
from envs.manipulation_truth import global_graph, local_graph
from envs.registry import EnvOptions, env_entry
from envs.skills import grasp
from services.runtime.config import build_config
from services.supervisor.config import RunConfig

SCENE = 17
CD, UD = slice(SCENE, SCENE + 20), slice(SCENE + 20, SCENE + 40)
ACTION = SCENE + 40


@pytest.fixture(scope="module")
def env() -> BlockEnv:
    env = BlockEnv()
    yield env
    env.close()


def test_factors_spec_and_gymnasium_contract(env: BlockEnv) -> None:
    obs, _ = env.reset(seed=0)
    assert obs.shape == (57,) and env.factor_names[:SCENE] == BLOCK.factor_names
    assert BLOCK.factor_names[5:8] == ("mov1.x", "mov1.y", "mov1.z") and BLOCK.factor_names[-3:] == ("unm.x", "unm.y", "unm.z")
    assert env.factor_names[SCENE] == "cd.0" and env.factor_names[-1] == "ud.19"
    np.testing.assert_array_equal(obs[CD], 0.0)  # controllable distractors start at 0
    np.testing.assert_allclose(obs[[7, 10, 13]], TABLE_TOP[2] + MOV_HALF, atol=1e-3)  # cubes rest on the table
    assert obs[16] == pytest.approx(TABLE_TOP[2] + FIXED_HALF)
    spec = env.env_spec()
    assert spec.env_id == "block" and spec.num_factors == 57 and spec.global_graph.shape == (57, 58)
    assert spec.factor_objects[SCENE:] == ("cd",) * 20 + ("ud",) * 20
    entry = env_entry("block")
    assert entry.constant_factors == ("unm.z",) and set(entry.tasks) == set(TASKS) and entry.has_local_truth
    np.testing.assert_array_equal(spec.reward_parents, task_reward_parents("pick", env.global_graph))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, skip_render_check=True)
    small = gym.make("causeway/Block-v0", task="stack", distractors="2,1", episode_length=5)
    assert small.reset(seed=0)[0].shape == (SCENE + 3,)
    small.close()


def test_distractors_have_exactly_the_parents_they_should(env: BlockEnv) -> None:
    graph = env.global_graph
    cd_rows = np.zeros((20, 58), np.uint8)
    cd_rows[:, ACTION] = 1
    cd_rows[np.arange(20), np.arange(SCENE, SCENE + 20)] = 1  # the self-edge every factor has
    np.testing.assert_array_equal(graph[CD], cd_rows)
    ud_rows = np.zeros((20, 58), np.uint8)
    ud_rows[np.arange(20), np.arange(SCENE + 20, SCENE + 40)] = 1
    np.testing.assert_array_equal(graph[UD], ud_rows)
    assert not graph[:SCENE, SCENE:ACTION].any()  # no scene factor reads a distractor
    np.testing.assert_array_equal(graph[:SCENE, :SCENE], global_graph(BLOCK)[:, :SCENE])
    # the simulator agrees: a distractor's value changes nothing next step; the action moves only cd
    env.reset(seed=2)
    action = np.array([0.5, -0.3, 0.2, 0.7])
    start, values = env.snapshot(), env._values.copy()
    base = env.step(action)
    for change in ({"cd.3": 0.9, "ud.7": -0.8}, None):
        env.restore(start)
        env.intervene({name: values[k] for k, name in enumerate(env.distractors.names)} | (change or {}))
        obs, reward, *_ = env.step(action if change else np.array([-0.5, 0.3, 0.2, 0.1]))
        if change:
            np.testing.assert_array_equal(obs, base[0])
            assert reward == base[1]
        else:
            assert not np.allclose(obs[CD], base[0][CD])
            np.testing.assert_array_equal(obs[UD], base[0][UD])
    np.testing.assert_allclose(base[0][CD], env.distractors.projection @ action, rtol=1e-6)


def test_reward_parents_and_minimal_abstraction_of_pick_and_stack() -> None:
    truth = Distractors(20, 20, "continuous", 4).extend_graph(global_graph(BLOCK))  # no simulator needed
    for task in TASKS:
        parents = task_reward_parents(task, truth)
        # any cube can block the arm, so every scene factor reaches eef and mov1 within a step
        np.testing.assert_array_equal(parents, np.r_[np.ones(SCENE), np.zeros(40), 1].astype(np.uint8))
        assert minimal_abstraction(truth, parents).kept == tuple(range(SCENE))
    # without contact, mov2 moves by itself only and the robot reads the action only
    quiet = local_graph(np.zeros((6, 6), bool), BLOCK)
    assert quiet[8:11].nonzero()[1].tolist() == [8, 9, 10] * 3 and not quiet[5:8, :5].any()
    pushed = np.zeros((6, 6), bool)
    pushed[0, 1] = pushed[1, 0] = pushed[1, 2] = pushed[2, 1] = True  # robot pushes mov1 into mov2
    chain = local_graph(pushed, BLOCK)
    assert chain[8:11, :8].all() and chain[8:11, SCENE].all() and not chain[11:14, :11].any()


def test_scripted_grasp_and_lift_reaches_pick_success(env: BlockEnv) -> None:
    obs, _ = env.reset(seed=3)
    skill, rewards = grasp("mov"), []  # mov1 has chapter 3's mov's factor indices
    for _ in range(60):
        obs, reward, terminated, _, info = env.step(skill.act(obs))
        rewards.append(reward)
        if terminated:
            break
    assert terminated and info["success"] and reward == 1.0
    assert obs[7] >= TABLE_TOP[2] + MOV_HALF + PICK_HEIGHT and max(rewards[:-1]) < 1.0
    assert info["local_graph"][5:8, :5].all()  # the held cube reads the robot


def test_stack_success_is_detected_from_the_state(env: BlockEnv) -> None:
    obs, _ = env.reset(seed=4)
    unm = obs[14:17]
    on_top = {"mov1.x": unm[0], "mov1.y": unm[1], "mov1.z": unm[2] + FIXED_HALF + MOV_HALF}
    obs = env.intervene(on_top | {"grp.0": 0.04, "grp.1": -0.04})
    assert task_reward("stack", obs) == (1.0, True) and not task_reward("pick", obs)[1]
    assert not task_reward("stack", env.intervene({"mov1.x": unm[0] + 0.05}))[1]
    assert not task_reward("stack", env.intervene(on_top | {"grp.0": 0.02, "grp.1": -0.02}))[1]  # still held


def test_bad_task_and_options_are_refused_with_the_valid_values() -> None:
    from services.supervisor.wiring import resolve

    with pytest.raises(ValueError, match=r"task must be one of \('pick', 'stack'\)"):
        BlockEnv(task="match")
    with pytest.raises(ValueError, match="poses no task 'match'; its tasks: pick, stack"):
        resolve(build_config(RunConfig, router_port=7447, env="block", task="match"))
    with pytest.raises(ValueError, match="'controllable,uncontrollable'"):
        EnvOptions(distractors="20")
    cfg = resolve(build_config(RunConfig, router_port=7447, env="block", task="stack", distractors="3,4"))
    assert env_entry(cfg.env).kwargs(cfg.env_options) == {"distractors": "3,4", "task": "stack"}
    # an option the env does not take would be ignored: refused, with the ones it takes
    with pytest.raises(ValueError, match=r"'chemical' does not take --velocities \(its options: --graph, "):
        resolve(build_config(RunConfig, router_port=7447, env="chemical", velocities=True))
    with pytest.raises(ValueError, match="'block' does not take --num-objects, --room-size"):
        resolve(build_config(RunConfig, router_port=7447, env="block", num_objects=3, room_size=8))
    cfg = resolve(build_config(RunConfig, router_port=7447, env="block", velocities=True))
    assert env_entry(cfg.env).kwargs(cfg.env_options) == {"distractors": "20,20", "velocities": True}
    # a run is named by its Chemical graph only on Chemical, else by its method
    assert cfg.run_id.startswith("block-cdl-s0-")
    assert resolve(build_config(RunConfig, router_port=7447, env="chemical")).run_id.startswith("chemical-full-s0-")


def test_a_seed_fixes_the_episode(env: BlockEnv) -> None:
    actions = np.random.default_rng(0).uniform(env.action_space.low, env.action_space.high, (8, 4))
    fresh = BlockEnv()

    def rollout(e: BlockEnv, seed: int) -> np.ndarray:
        first, _ = e.reset(seed=seed)
        return np.array([first] + [e.step(a)[0] for a in actions])

    a, b, other = rollout(env, 5), rollout(fresh, 5), rollout(env, 6)
    fresh.close()
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a[0, 5:14], other[0, 5:14]) and not np.allclose(a[:, UD], other[:, UD])


def test_velocity_factors_follow_the_positions_and_leave_the_dynamics_alone(env: BlockEnv) -> None:
    """``velocities=True``: 20 velocity factors after the 17 positions (which keep their indices),
    each in its body's block of the truth; the same seed and actions give the same positions, rewards
    and distractors; the velocities are the simulator's (the end-effector's agrees with its motion)."""
    layout = BLOCK.with_velocities()
    assert layout.factor_names[:SCENE] == BLOCK.factor_names and layout.num_factors == SCENE + 20
    assert layout.factor_names[SCENE:SCENE + 11] == tuple(f"eef.{d}" for d in ("vx", "vy", "vz", "rx", "ry", "rz", "wx", "wy",
                                                                              "wz")) + ("grp.v0", "grp.v1")
    assert layout.factor_slice("mov1") == BLOCK.factor_slice("mov1")
    assert layout.factor_indices("mov1").tolist() == [5, 6, 7, SCENE + 11, SCENE + 12, SCENE + 13]
    truth, plain = global_graph(layout), global_graph(BLOCK)
    np.testing.assert_array_equal(truth[:SCENE, :SCENE], plain[:, :SCENE])
    np.testing.assert_array_equal(truth[:SCENE, -1], plain[:, -1])
    eef = layout.factor_indices("eef")
    assert truth[np.ix_(eef, eef)].all() and truth[eef, -1].all()
    assert truth[np.ix_(layout.factor_indices("mov2"), layout.factor_indices("unm"))].all()  # unm blocks mov2
    quiet = local_graph(np.zeros((6, 6), bool), layout)
    mov2 = layout.factor_indices("mov2")
    assert quiet[mov2].nonzero()[1].tolist() == mov2.tolist() * 6  # a resting cube reads only itself

    fast = BlockEnv(velocities=True, task="pick")
    try:
        spec = fast.env_spec()
        assert spec.num_factors == SCENE + 20 + 40 and spec.global_graph.shape == (77, 78)
        assert spec.factor_names[SCENE + 20] == "cd.0" and spec.factor_objects[SCENE:SCENE + 11] == ("eef",) * 9 + ("grp",) * 2
        assert spec.factor_locs[SCENE:SCENE + 9] == (0.0,) * 9
        np.testing.assert_allclose(spec.factor_scales[SCENE:SCENE + 9], [0.1] * 3 + [0.01] * 3 + [0.1] * 3)
        np.testing.assert_array_equal(spec.reward_parents[:SCENE], env.reward_parents[:SCENE])
        actions = np.tile([1.0, 0.0, 0.0, 1.0], (6, 1))
        obs_v, _ = fast.reset(seed=7)
        obs, _ = env.reset(seed=7)
        np.testing.assert_array_equal(obs_v[:SCENE], obs[:SCENE])
        np.testing.assert_allclose(obs_v[SCENE:SCENE + 20], 0.0, atol=1e-3)  # everything at rest, as at reset
        for a in actions:
            step_v, step = fast.step(a), env.step(a)
            np.testing.assert_array_equal(step_v[0][:SCENE], step[0][:SCENE])
            np.testing.assert_array_equal(step_v[0][SCENE + 20:], step[0][SCENE:])
            assert step_v[1] == step[1]
        # the arm moves along +x at about the speed its positions show (the goal runs 3 cm ahead)
        moved = (step_v[0][0] - obs_v[0]) / (len(actions) / fast.control_freq)
        assert step_v[0][SCENE] > 0.5 * moved > 0 and abs(step_v[0][SCENE]) < 0.5
        np.testing.assert_allclose(step_v[0][SCENE + 11:SCENE + 20], 0.0, atol=1e-3)  # untouched cubes rest
        rotation, spin = step_v[0][SCENE + 3:SCENE + 6], step_v[0][SCENE + 6:SCENE + 9]
        assert 0 < np.abs(rotation).max() < 0.05 and np.abs(spin).max() < 1.0  # the held orientation wobbles
        with pytest.raises(KeyError, match="cannot intervene on 'mov1.vx'"):
            fast.intervene({"mov1.vx": 0.1})
    finally:
        fast.close()
    assert env_entry("block").kwargs(EnvOptions(velocities=True))["velocities"] is True
    assert "velocities" not in env_entry("block").kwargs(EnvOptions())
