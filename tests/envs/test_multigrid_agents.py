"""MultiGrid agents (FLAM's data, ch. 8): seeding, frames and exact masks, solid agents, the
correlated variant, recorded videos, the registry entries and the gymnasium contract."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from envs import make_env
from envs.chemical_pixels import PALETTE
from causal.dci import dci
from envs.demonstrations import record_demonstrations
from envs.multigrid_agents import (MOVES, NUM_MOVES, CorrelatedMultiGridAgentsEnv, MultiGridAgentsEnv, MultiGridGoalEnv,
                                  displacement_codes, goal_expert_action, record_videos)


def test_seeded_episodes_repeat_frame_for_frame() -> None:
    runs = []
    for _ in range(2):
        env = MultiGridAgentsEnv()
        _, info = env.reset(seed=3)
        runs.append(np.stack([info["frame"]] + [env.step(a)[4]["frame"] for a in (0, 7, 313, 624)]))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(MultiGridAgentsEnv().reset(seed=4)[1]["frame"], runs[0][0])


def test_frame_masks_and_colours_follow_positions() -> None:
    env = MultiGridAgentsEnv(cell_pixels=6)
    obs, info = env.reset(seed=1)
    assert info["frame"].shape == (48, 48, 3) and info["masks"].shape == (5, 48, 48)
    np.testing.assert_array_equal(info["masks"].sum(axis=0), 1)
    np.testing.assert_array_equal(info["frame"][info["masks"][0]], 0)
    for i, (x, y) in enumerate(obs.reshape(-1, 2).astype(int)):
        ys, xs = np.nonzero(info["masks"][1 + i])
        assert len(xs) == 36 and xs.min() == 6 * x and ys.min() == 6 * y
        assert (info["frame"][info["masks"][1 + i]] == PALETTE[i]).all()


def test_each_agent_moves_by_its_own_digit() -> None:
    env = MultiGridAgentsEnv()
    env.reset(seed=0)
    env._positions = np.array([[1, 1], [5, 5], [1, 6], [6, 1]])
    actions = np.array([1, 2, 3, 4])
    _, _, _, _, info = env.step(env.joint_action(actions))
    np.testing.assert_array_equal(info["agent_actions"], actions)
    np.testing.assert_array_equal(env._positions, np.array([[1, 1], [5, 5], [1, 6], [6, 1]]) + MOVES[actions])


def test_walls_and_other_agents_block_moves() -> None:
    env = MultiGridAgentsEnv(num_agents=3)
    start = np.array([[0, 0], [2, 3], [3, 3]])
    # agent 0 walks into the top wall, agent 1 into agent 2, agent 2 right (free)
    moved = env.transition(start, np.array([1, 4, 4]))
    np.testing.assert_array_equal(moved, [[0, 0], [2, 3], [4, 3]])
    # agent 1 moves first into the cell agent 2 leaves afterwards: blocked (agents move in order)
    assert len({tuple(p) for p in moved}) == 3


def test_correlated_variant_copies_agent_zeros_action() -> None:
    env = CorrelatedMultiGridAgentsEnv()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        _, _, _, _, info = env.step(int(rng.integers(env.action_space.n)))
        assert info["agent_actions"][1] == info["agent_actions"][0]
    plain = MultiGridAgentsEnv().agent_actions(MultiGridAgentsEnv().joint_action(np.array([1, 2, 3, 4])))
    np.testing.assert_array_equal(plain, [1, 2, 3, 4])


def test_recorded_videos_are_seeded_and_consistent() -> None:
    env = MultiGridAgentsEnv()
    video = record_videos(env, episodes=3, steps=6, seed=5)
    again = record_videos(MultiGridAgentsEnv(), episodes=3, steps=6, seed=5)
    for key in video:
        np.testing.assert_array_equal(video[key], again[key])
    assert video["frames"].shape == (3, 7, 32, 32, 3) and video["actions"].shape == (3, 6, 4)
    step = env.transition(video["positions"][1, 2], video["actions"][1, 2])
    np.testing.assert_array_equal(step, video["positions"][1, 3])
    frames, _ = env.render_positions(video["positions"][2])
    np.testing.assert_array_equal(frames, video["frames"][2])
    correlated = record_videos(CorrelatedMultiGridAgentsEnv(), episodes=2, steps=30, seed=0)["actions"]
    np.testing.assert_array_equal(correlated[..., 0], correlated[..., 1])
    assert (correlated[..., 0] != correlated[..., 2]).any()


def test_registry_spec_and_config_round_trip() -> None:
    env = make_env("multigrid-agents-correlated", episode_length=9, render_mode="rgb_array")
    _, info = env.reset(seed=0)
    np.testing.assert_array_equal(env.render(), info["frame"])
    spec = env.unwrapped.env_spec()
    assert spec.env_id == "multigrid-agents-correlated" and spec.action_size == 625 and spec.num_factors == 8
    assert MultiGridAgentsEnv(**json.loads(spec.config_json)).config() == env.unwrapped.config()
    assert make_env("multigrid-agents").unwrapped.env_spec().env_id == "multigrid-agents"


def test_bad_options_are_refused() -> None:
    with pytest.raises(ValueError, match="num_agents"):
        MultiGridAgentsEnv(num_agents=11)
    with pytest.raises(ValueError, match="correlated"):
        MultiGridAgentsEnv(num_agents=1, correlated=True)
    with pytest.raises(ValueError, match="action"):
        MultiGridAgentsEnv().step(625)


@pytest.mark.parametrize("cls", [MultiGridAgentsEnv, CorrelatedMultiGridAgentsEnv])
def test_gymnasium_check_env(cls: type[MultiGridAgentsEnv]) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(cls(), skip_render_check=True)


def test_displacement_codes_are_the_observed_moves_and_a_blocked_move_looks_like_a_stay() -> None:
    # one episode, two agents: agent 0 moves right then stays; agent 1 pushes into the wall (x = 0) then moves down
    positions = np.array([[[[2, 2], [0, 3]], [[3, 2], [0, 3]], [[3, 2], [0, 4]]]])
    codes = displacement_codes(positions)
    assert codes.shape == (2, 2, 9) and np.all(codes.sum(-1) == 1.0)
    offsets = [[(int(i) // 3 - 1, int(i) % 3 - 1) for i in row] for row in codes.argmax(-1)]
    assert offsets == [[(1, 0), (0, 0)], [(0, 0), (0, 1)]]  # agent 1's blocked step codes as a stay
    with pytest.raises(ValueError, match="more than one cell"):
        displacement_codes(np.array([[[[0, 0]], [[2, 0]]]]))


def test_the_observed_moves_read_the_actions_well_but_not_perfectly() -> None:
    """The ceiling of FLAM's latent actions against the actions: blocked moves cannot be read from frames."""
    videos = record_videos(MultiGridAgentsEnv(num_agents=4, grid_size=8), 40, 10, seed=7)
    scores = dci(torch.from_numpy(displacement_codes(videos["positions"])),
                 torch.from_numpy(videos["actions"]).reshape(-1, 4), classes=NUM_MOVES)
    assert 0.6 < scores.informativeness < 0.97
    assert scores.importance.argmax(0).tolist() == [0, 1, 2, 3]  # each agent's action is read from its own move


def test_the_goal_task_pays_for_reaching_the_goal_and_moves_it_to_a_free_cell() -> None:
    env = MultiGridGoalEnv(num_agents=3, grid_size=5)
    obs, info = env.reset(seed=4)
    assert obs.shape == (8,) and info["masks"].shape == (5, 20, 20)
    assert info["masks"].sum(0).max() == 1  # the masks partition the frame
    assert not (env._positions == env.goal).all(axis=1).any()  # the goal starts on a free cell
    assert (info["frame"][info["masks"][4]] == PALETTE[3]).all() and info["masks"][4].sum() == 16
    # put the player next to the goal, the others out of the way, and step onto it
    env._positions = np.array([[0, 0], [4, 4], [4, 3]])
    env.goal = np.array([1, 0])
    _, reward, terminated, truncated, info = env.step(4)
    assert reward == 1.0 and info["goals"] == 1 and info["success"] and not terminated and not truncated
    assert info["agent_actions"][0] == 4 and (env._positions[0] == (1, 0)).all()
    assert not (env._positions == env.goal).all(axis=1).any()
    _, reward, *_ = env.step(0)
    assert reward == 0.0
    with pytest.raises(ValueError, match="action"):
        env.step(5)
    with pytest.raises(ValueError, match="goal takes a colour"):
        MultiGridGoalEnv(num_agents=len(PALETTE))
    spec = MultiGridGoalEnv(num_agents=3, grid_size=5).env_spec()
    assert spec.factor_names[-2:] == ("goal.x", "goal.y") and len(spec.factor_names) == 8
    assert spec.action_size == NUM_MOVES and MultiGridGoalEnv(**json.loads(spec.config_json)).grid_size == 5


def test_the_goal_tasks_episodes_repeat_under_a_seed_whatever_the_others_do() -> None:
    def episode(seed: int) -> list[np.ndarray]:
        env = MultiGridGoalEnv()
        frames = [env.reset(seed=seed)[1]["frame"]]
        for t in range(20):
            frames.append(env.step(t % NUM_MOVES)[4]["frame"])
        return frames
    first, again, other = episode(3), episode(3), episode(4)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert not all(np.array_equal(a, b) for a, b in zip(first, other))


def test_the_goal_expert_walks_to_the_goal_around_agents() -> None:
    env = MultiGridGoalEnv(num_agents=2, grid_size=6)
    env.reset(seed=0)
    env._positions, env.goal = np.array([[1, 1], [5, 5]]), np.array([4, 2])
    assert goal_expert_action(env) == 4  # x is the longer way: right
    env._positions = np.array([[1, 1], [2, 1]])  # an agent holds the cell to the right: go down
    assert goal_expert_action(env) == 2
    env.goal = np.array([1, 0])
    env._positions = np.array([[1, 1], [1, 0]])  # the only way is held: the move is tried (blocked)
    assert goal_expert_action(env) == 1
    # the expert collects many goals, a random policy few
    expert = record_demonstrations(MultiGridGoalEnv(), 500, 0, 0.0, goal_expert_action, lambda e: e.render_scene())
    random = record_demonstrations(MultiGridGoalEnv(), 500, 0, 1.0, goal_expert_action, lambda e: e.render_scene())
    assert expert["returns"].mean() > 6.0 and random["returns"].mean() < 1.5
    assert 0 not in expert["actions"] and expert["labels"].max() == 5
    assert len(expert["frames"]) == len(expert["actions"]) + len(expert["returns"])


def test_the_goal_task_passes_gymnasiums_checker() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(MultiGridGoalEnv(), skip_render_check=True)
