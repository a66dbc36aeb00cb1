"""The bigfish-like sprite game (issue 24): exact occlusion-aware masks, painter's order, seeding,
the factor layout and spec, the local graph of eat events, refused options, the registry entry."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from envs import make_env
from envs.registry import EnvOptions, check_options, env_entry
from envs.sprites import (ALIVE, AGENT_STEP, COLOR, FIELDS, NUM_FIELDS, SIZE, VX, X, Y, SpritesEnv, expert_action,
                          record_demonstrations, record_frames)


def _run(env: SpritesEnv, seed: int, steps: int) -> list[tuple[np.ndarray, dict]]:
    obs, info = env.reset(seed=seed)
    out = [(obs, {**info, "background": env._background.copy()})]
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(int(rng.integers(env.num_moves)))
        out.append((obs, {**info, "background": env._background.copy()}))
        if terminated or truncated:
            obs, info = env.reset()
            out.append((obs, {**info, "background": env._background.copy()}))
    return out


def test_masks_are_exactly_each_objects_visible_pixels() -> None:
    env = SpritesEnv(num_fish=6)
    for obs, info in _run(env, seed=1, steps=40):
        state = obs.reshape(env.num_objects, NUM_FIELDS).astype(np.float64)
        masks, frame = info["masks"], info["frame"]
        assert masks.shape == (env.num_objects + 1, 32, 32)
        np.testing.assert_array_equal(masks.sum(axis=0), 1)  # a partition
        order = list(range(1, env.num_objects)) + [0]  # painter's order: fish, then the agent
        drawn = {o: np.logical_or.reduce(env.sprite_parts(state[o])) if state[o, ALIVE] > 0.5
                 else np.zeros((32, 32), bool) for o in order}
        for rank, o in enumerate(order):
            hidden = np.logical_or.reduce([drawn[later] for later in order[rank + 1:]] + [np.zeros((32, 32), bool)])
            np.testing.assert_array_equal(masks[1 + o], drawn[o] & ~hidden)
        # the background shows where no object is, and each object's pixels are its own colours
        np.testing.assert_array_equal(frame[masks[0]], info["background"][masks[0]])
        for o in order:
            if masks[1 + o].any():
                alone, _ = env.render_state(np.where(np.arange(env.num_objects)[:, None] == o, state,
                                                     state * np.array([1, 1, 1, 1, 1, 0])), info["background"])
                np.testing.assert_array_equal(frame[masks[1 + o]], alone[masks[1 + o]])


def test_later_sprites_hide_earlier_ones_and_the_agent_is_on_top() -> None:
    env = SpritesEnv(num_fish=2)
    env.reset(seed=0)
    state = np.array([[0.0, 0.0, 0.0, 0.14, 0.0, 1.0],
                      [0.05, 0.0, 0.03, 0.25, 1.0, 1.0],
                      [0.1, 0.02, -0.03, 0.2, 2.0, 1.0]])
    _, labels = env.render_state(state)
    parts = [np.logical_or.reduce(env.sprite_parts(state[o])) for o in range(3)]
    assert (parts[1] & parts[2]).any() and (parts[0] & parts[2]).any()
    assert (labels[parts[0]] == 1).all()  # the agent wins every overlap
    assert (labels[parts[2] & ~parts[0]] == 3).all()  # fish 2 over fish 1
    assert ((labels == 2) == (parts[1] & ~parts[2] & ~parts[0])).all()
    # more than one colour per sprite: the fish's visible pixels are not one colour
    frame, _ = env.render_state(state)
    assert len(np.unique(frame[labels == 2], axis=0)) >= 2


def test_seeded_episodes_repeat_and_seeds_differ() -> None:
    runs = [np.stack([info["frame"] for _, info in _run(SpritesEnv(), seed=5, steps=30)]) for _ in range(2)]
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(SpritesEnv().reset(seed=6)[1]["frame"], runs[0][0])
    a, b = record_frames(SpritesEnv(), 2, 50), record_frames(SpritesEnv(), 2, 50)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_background_is_textured() -> None:
    env = SpritesEnv(frame_size=64)
    _, info = env.reset(seed=0)
    background = info["frame"][info["masks"][0]]
    assert len(np.unique(background, axis=0)) > 50


def test_factor_layout_and_spec() -> None:
    env = SpritesEnv(num_fish=3, num_colors=5, num_moves=9)
    obs, _ = env.reset(seed=0)
    spec = env.env_spec()
    assert spec.env_id == "sprites" and spec.num_factors == 4 * len(FIELDS) == len(obs)
    assert spec.factor_names[:6] == tuple(f"agent.{f}" for f in FIELDS)
    assert spec.factor_names[6 * 3 + COLOR] == "fish3.color" and spec.factor_sizes[6 * 3 + COLOR] == 5
    assert spec.factor_kinds[ALIVE] == "categorical" and spec.factor_kinds[X] == "continuous"
    assert spec.action_size == 9 and spec.state_dim == len(obs)
    state = obs.reshape(4, NUM_FIELDS)
    assert state[0, COLOR] == 0 and state[0, VX] == 0 and (state[1:, COLOR] >= 1).all()
    rebuilt = SpritesEnv(**json.loads(spec.config_json)).env_spec()
    assert rebuilt.config_json == spec.config_json and rebuilt.factor_names == spec.factor_names
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(SpritesEnv(), skip_render_check=True)
    for obs, _ in _run(env, seed=3, steps=200):
        assert env.observation_space.contains(obs)


def test_moves_and_fish_speeds() -> None:
    env = SpritesEnv(num_fish=1, num_moves=9)
    env.reset(seed=0)
    state = np.array([[0.0, 0.0, 0.0, 0.14, 0.0, 1.0], [-0.8, 0.7, 0.05, 0.1, 1.0, 1.0]])
    new, graph, reward, eaten, dead = env.transition(state, 8)  # down-right
    np.testing.assert_allclose(new[0, [X, Y]], [0.08, 0.08])
    np.testing.assert_allclose(new[1, X], -0.75)
    assert (reward, eaten, dead) == (0.0, 0, False)
    assert graph[X, -1] == 1 and graph[Y, -1] == 1 and graph[SIZE, -1] == 0
    assert graph[NUM_FIELDS + X, NUM_FIELDS + VX] == 1
    np.testing.assert_array_equal(np.diag(graph[:, :-1]), 1)
    assert graph.sum() == 12 + 3  # self-edges, action -> agent x and y, fish vx -> x


def test_eat_event_local_graph() -> None:
    env = SpritesEnv(num_fish=2)
    env.reset(seed=0)
    state = np.array([[0.0, 0.0, 0.0, 0.2, 0.0, 1.0],
                      [0.05, 0.0, 0.02, 0.1, 1.0, 1.0],  # smaller and touching: eaten
                      [-0.8, 0.8, -0.03, 0.25, 2.0, 1.0]])  # far away
    new, graph, reward, eaten, dead = env.transition(state, 0)
    assert (reward, eaten, dead) == (1.0, 1, False)
    assert new[0, SIZE] == pytest.approx(0.22) and new[1, ALIVE] == 0
    agent = lambda f: f  # noqa: E731
    fish = lambda i, f: i * NUM_FIELDS + f  # noqa: E731
    contact = {agent(X), agent(Y), agent(SIZE), fish(1, X), fish(1, Y), fish(1, VX), fish(1, SIZE), fish(1, ALIVE)}
    for child in (agent(SIZE), fish(1, ALIVE)):
        assert set(np.flatnonzero(graph[child, :-1])) == contact and graph[child, -1] == 1
    # no edge between the agent and the far fish, and nothing into the agent's position from the fish
    assert graph[:NUM_FIELDS, 2 * NUM_FIELDS:-1].sum() == 0 and graph[2 * NUM_FIELDS:, :NUM_FIELDS].sum() == 0
    assert graph[agent(X), NUM_FIELDS:-1].sum() == 0
    # the next step respawns the eaten fish: each of its factors from its alive
    env._state = new
    _, _, _, _, info = env.step(0)
    assert env._state[1, ALIVE] == 1 and abs(env._state[1, X]) > 1.0
    np.testing.assert_array_equal(info["local_graph"][NUM_FIELDS:2 * NUM_FIELDS, fish(1, ALIVE)], 1)


def test_a_bigger_fish_ends_the_episode_and_winning_pays_ten() -> None:
    env = SpritesEnv(num_fish=1)
    env.reset(seed=0)
    env._state = np.array([[0.0, 0.0, 0.0, 0.14, 0.0, 1.0], [0.1, 0.0, -0.02, 0.2, 1.0, 1.0]])
    _, reward, terminated, _, info = env.step(0)
    assert terminated and reward == 0 and env._state[0, ALIVE] == 0 and not info["masks"][1].any()
    assert info["local_graph"][ALIVE, NUM_FIELDS + SIZE] == 1
    env.reset(seed=0)
    env._state = np.array([[0.0, 0.0, 0.0, 0.31, 0.0, 1.0], [0.1, 0.0, -0.02, 0.1, 1.0, 1.0]])
    _, reward, terminated, _, info = env.step(0)
    assert terminated and reward == 11.0 and info["success"]


def test_bad_options_are_refused() -> None:
    for kwargs in ({"num_fish": 0}, {"num_colors": 1}, {"num_moves": 4}, {"frame_size": 48},
                   {"episode_length": 0}, {"render_mode": "human"}):
        with pytest.raises(ValueError):
            SpritesEnv(**kwargs)
    with pytest.raises(ValueError):
        check_options("sprites", EnvOptions(episode_length=-1))
    check_options("sprites", EnvOptions(episode_length=7))


def test_registry_entry_builds_the_game() -> None:
    entry = env_entry("sprites")
    assert entry.has_local_truth and not entry.has_global_truth
    env = make_env("sprites", **entry.kwargs(EnvOptions(episode_length=7)))
    assert env.episode_length == 7 and env.env_spec().env_id == "sprites"
    import gymnasium as gym

    made = gym.make("causeway/Sprites-v0", frame_size=64, render_mode="rgb_array")
    made.reset(seed=0)
    assert made.render().shape == (64, 64, 3)


def _episode_returns(env: SpritesEnv, act, seeds: range) -> list[float]:
    returns = []
    for seed in seeds:
        env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(act(env))
            total, done = total + reward, terminated or truncated
        returns.append(total)
    return returns


def test_the_scripted_expert_far_outscores_random_play() -> None:
    env, rng = SpritesEnv(), np.random.default_rng(0)
    expert = _episode_returns(env, lambda e: expert_action(e._state, e.num_moves), range(100, 110))
    random = _episode_returns(env, lambda e: int(rng.integers(e.num_moves)), range(100, 110))
    assert np.mean(expert) > 5.0 > 1.0 > np.mean(random)


def test_the_expert_flees_a_bigger_fish_and_takes_a_smaller_one() -> None:
    env = SpritesEnv(num_fish=1)
    env.reset(seed=0)
    state = env._state.copy()
    state[0, [X, Y, SIZE]] = (0.0, 0.0, 0.14)
    # a bigger fish just right of the agent, swimming at it: moving left (3) is the one escape
    state[1] = (0.40, 0.0, -0.08, 0.25, 1.0, 1.0)
    assert expert_action(state, 5) == 3
    # a smaller fish one step above: up (1) eats it
    state[1] = (0.0, -AGENT_STEP - 0.05, 0.0, 0.08, 1.0, 1.0)
    assert expert_action(state, 5) == 1
    # 9 moves: the same escape is still a leftward move
    state[1] = (0.40, 0.0, -0.08, 0.25, 1.0, 1.0)
    assert expert_action(state, 9) in (3, 5, 7)


def test_demonstrations_are_whole_episodes_of_the_expert() -> None:
    env = SpritesEnv(num_fish=2)
    demos = record_demonstrations(env, 50, seed=3)
    frames, current, actions, episode = demos["frames"], demos["current"], demos["actions"], demos["episode"]
    assert len(actions) >= 50 and len(current) == len(actions) == len(episode)
    assert len(frames) == len(demos["labels"]) == len(actions) + len(demos["returns"])
    assert np.all(np.diff(episode) >= 0) and episode[-1] == len(demos["returns"]) - 1
    # replaying the first episode from its seed gives the same frames and the expert's actions
    env.reset(seed=3)
    for t in np.flatnonzero(episode == 0):
        assert np.array_equal(frames[current[t]], env.render_state(env._state)[0])
        assert actions[t] == expert_action(env._state, env.num_moves)
        env.step(int(actions[t]))
    assert np.array_equal(frames[current[t] + 1], env.render_state(env._state)[0])
    noisy = record_demonstrations(env, 300, seed=3, epsilon=1.0)
    assert len(np.unique(noisy["actions"])) == env.num_moves
    with pytest.raises(ValueError, match="epsilon"):
        record_demonstrations(env, 10, seed=0, epsilon=1.5)
