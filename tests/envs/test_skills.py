"""Scripted skills and the Uniform skill policy: each skill does what it says in the simulator, and the
policy meets the env-worker's policy contract and collects contact-rich data."""
from __future__ import annotations

import numpy as np
import pytest
from gymnasium.spaces import Box

from envs.manipulation import ManipulationEnv
from envs.manipulation_layout import (
    EEF, GRP, MOV, MOV_BODY, RAND, ROBOT, TABLE_TOP, UNM, UNM_BODY, WORKSPACE_HIGH, WORKSPACE_LOW,
)
from envs.skills import SKILLS, Skill, SkillPolicy, grasp, push, reach

CLEAR = {"mov.x": 0.0, "mov.y": 0.0, "unm.x": 0.12, "unm.y": 0.15, "rand.x": -0.12, "rand.y": 0.15}
"""Cubes placed so that the skills' paths are clear of ``unm`` and ``rand``."""


@pytest.fixture(scope="module")
def env() -> ManipulationEnv:
    env = ManipulationEnv(random_walk_step=0.0)  # rand stays where a test puts it
    yield env
    env.close()


def _run(env: ManipulationEnv, skill: Skill, obs: np.ndarray) -> tuple[np.ndarray, int]:
    steps = 0
    while (action := skill.act(obs)) is not None:
        assert env.action_space.contains(action)
        obs, *_ = env.step(action)
        steps += 1
    return obs, steps


def test_reach_gets_within_a_centimetre(env: ManipulationEnv) -> None:
    env.reset(seed=0)
    obs = env.intervene(CLEAR)
    target = np.array([0.05, -0.1, 0.9])
    obs, steps = _run(env, reach(target, opening=0.5), obs)
    assert np.linalg.norm(obs[EEF] - target) < 0.01 and steps <= 25
    assert 0.018 < obs[GRP][0] < 0.022  # half open: each finger at half its 4 cm travel


def test_grasp_lifts_the_movable_cube_and_push_moves_it(env: ManipulationEnv) -> None:
    env.reset(seed=1)
    obs = env.intervene(CLEAR)
    obs, steps = _run(env, grasp("mov"), obs)
    assert obs[MOV][2] > TABLE_TOP[2] + 0.08 and steps <= 45
    assert np.linalg.norm(obs[MOV][:2] - obs[EEF][:2]) < 0.01
    obs, _ = _run(env, reach(obs[EEF] - [0, 0, 0.1], opening=1.0), obs)  # put it down, let go
    start = obs[MOV].copy()
    direction = np.pi / 2
    obs, _ = _run(env, push("mov", direction, 0.08), obs)
    moved = obs[MOV] - start
    assert moved[1] > 0.05 and abs(moved[0]) < 0.02 and abs(moved[2]) < 0.005


def _lift_rise(env: ManipulationEnv, obj: str, seed: int) -> tuple[float, int, np.ndarray]:
    """Mean rise per step over the first 5 lift steps of ``grasp(obj)``, the lift steps touching
    ``unm``, and where ``unm`` ended up."""
    env.reset(seed=seed)
    obs = env.intervene(CLEAR)
    skill, rises, touching = grasp(obj), [], 0
    while (action := skill.act(obs)) is not None:
        phase = skill.phase
        nxt, *_ = env.step(action)
        if phase == "lift":
            rises.append(nxt[EEF][2] - obs[EEF][2])
            touching += env.scene.contacts[ROBOT, UNM_BODY]
        obs = nxt
    return float(np.mean(rises[:5])), int(touching), obs[UNM]


def test_grasping_the_fixed_cube_holds_the_arm_back(env: ManipulationEnv) -> None:
    """The action-relevant edge unm -> eef that the policy's grasps of unm put in the data: fingers
    closed on the fixed cube slow the lift that lifts the movable cube freely, and unm stays put."""
    free, _, _ = _lift_rise(env, "mov", seed=1)
    held, touching, unm_after = _lift_rise(env, "unm", seed=1)
    np.testing.assert_allclose(unm_after, [CLEAR["unm.x"], CLEAR["unm.y"], unm_after[2]], atol=1e-6)
    assert touching >= 3 and held < 0.6 * free, (held, free, touching)


def test_skill_policy_meets_the_policy_contract_without_a_simulator() -> None:
    space = Box(np.array([-1, -1, -1, 0], np.float32), np.ones(4, np.float32), dtype=np.float32)
    a, b = SkillPolicy(space, seed=3), SkillPolicy(space, seed=3)
    assert a.version == 0
    obs = np.zeros(23, np.float32)
    obs[EEF], obs[MOV] = [0.0, 0.0, 0.95], [0.05, 0.05, TABLE_TOP[2] + 0.02]
    names = set()
    for _ in range(400):  # a crude stand-in for the arm: the end-effector goes where it is sent
        action = a.act(obs)
        np.testing.assert_array_equal(action, b.act(obs))
        assert action.dtype == np.float32 and action.shape == (4,) and space.contains(action)
        names.add(a.skill.name)
        obs[EEF] = np.clip(obs[EEF] + 0.03 * action[:3], WORKSPACE_LOW, WORKSPACE_HIGH)
    assert names == set(SKILLS)
    with pytest.raises(ValueError):
        SkillPolicy(space, seed=0, skills=("fly",))
    with pytest.raises(ValueError):
        SkillPolicy(space, seed=0, grasp_objects=("marker",))
    obs[UNM], obs[RAND] = [0.1, 0.1, TABLE_TOP[2] + 0.025], [-0.1, 0.1, TABLE_TOP[2] + 0.025]
    grasped = {SkillPolicy(space, seed=s, skills=("grasp",)).sample_skill().phases[0].target(obs, obs)[0]
               for s in range(30)}  # the x of the hover point above each cube: unm and rand are grasped too
    assert len(grasped) == 3


def test_skill_policy_moves_touches_and_holds(env: ManipulationEnv) -> None:
    policy = SkillPolicy(env.action_space, seed=1, grasp_objects=("mov",))  # grasps of unm: test above
    obs, _ = env.reset(seed=1)
    path, touching, lifted = 0.0, 0, 0
    for _ in range(80):
        previous = obs[EEF]
        obs, *_ = env.step(policy.act(obs))
        path += np.linalg.norm(obs[EEF] - previous)
        touching += env.scene.contacts[ROBOT, MOV_BODY]
        lifted += obs[MOV][2] > TABLE_TOP[2] + 0.05
    assert path > 0.5 and touching >= 20 and lifted >= 5
