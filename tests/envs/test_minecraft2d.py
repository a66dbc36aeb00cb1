"""2D Minecraft: gymnasium contract, seeding, the technology tree's rules, stages, the scripted
policy, and the true local graphs checked against the simulator by interventions."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.utils.passive_env_checker import env_render_passive_checker

from envs.household.scripted import RandomPrimitivePolicy
from envs.minecraft2d import ITEMS, MAX_COUNT, Minecraft2DEnv, Minecraft2DPolicy
from proto.codec import decode, encode
from proto.messages import EnvSpec
from tests.envs.intervention import assert_global_graph_is_the_union, edge_names, intervened_graph, random_box_state


def _play(env: Minecraft2DEnv, seed: int) -> tuple[list[np.ndarray], list[dict], bool]:
    policy = Minecraft2DPolicy(env)
    obs, _ = env.reset(seed=seed)
    observations, infos = [], []
    while True:
        observations.append(obs)
        obs, _, terminated, truncated, info = env.step(int(policy.act(obs)[0]))
        infos.append(info)
        if terminated or truncated:
            return observations, infos, terminated


def _facing(env: Minecraft2DEnv, obj: str, **inventory: int) -> np.ndarray:
    """A state with the agent in front of ``obj`` (after ``goTo``) and the given inventory."""
    obs, _ = env.reset(seed=0)
    obs = env.transition(obs, env.action_index("goTo", obj))[0]
    for item in ITEMS:
        obs[env.layout[f"inventory.{item}"]] = inventory.get(item, 0)
    return obs


def test_check_env_passes_without_warnings() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(Minecraft2DEnv(), skip_render_check=True)
        check_env(Minecraft2DEnv(goal="stone", room_size=8), skip_render_check=True)
        env = Minecraft2DEnv(render_mode="ansi")
        env.reset(seed=0)
        env_render_passive_checker(env)
    assert env.render().count("\n") == 16


def test_reset_seed_makes_the_episode_reproducible() -> None:
    actions = np.random.default_rng(0).integers(15, size=700).tolist()

    def rollout(seed: int) -> np.ndarray:
        env = Minecraft2DEnv()
        out = [env.reset(seed=seed)[0]]
        for a in actions:
            obs, _, terminated, truncated, info = env.step(a)
            out.append(np.r_[obs, info["local_graph"].ravel(), info["num_stages"]])
            if terminated or truncated:
                out.append(env.reset()[0])
        return np.concatenate(out)

    np.testing.assert_array_equal(rollout(7), rollout(7))
    assert not np.array_equal(rollout(7), rollout(8))


def test_layout_and_spec() -> None:
    env = Minecraft2DEnv()
    spec = env.env_spec()
    assert len(env.factor_names) == 24 and env.action_space.n == 15
    assert env.factor_names[-9:] == tuple(f"inventory.{i}" for i in ITEMS)
    assert spec.factor_sizes[-9:] == (MAX_COUNT + 1, MAX_COUNT + 1, 2, MAX_COUNT + 1, 2, MAX_COUNT + 1,
                                      MAX_COUNT + 1, 2, 2)
    assert spec.factor_sizes[:5] == (15, 15, 4, 15, 15) and spec.env_id == "minecraft2d"
    assert spec.factor_kinds == ("categorical",) * 24 and spec.episode_length == 300
    assert decode(encode(spec), EnvSpec).config_json == spec.config_json
    assert json.loads(spec.config_json) == {"goal": "diamond", "room_size": 16, "episode_length": 300}
    assert env.stage_names[0] == "collect wood" and env.stage_names[-1] == "mine diamond"
    assert Minecraft2DEnv(goal="iron").stage_names[-1] == "smelt iron"


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"goal": "gold"}, "goal must be one of .*'wood'.*'diamond'"),
    ({"room_size": 5}, r"room_size must be an integer in \[6, 32\]"),
    ({"episode_length": -1}, "episode_length"),
])
def test_bad_constructor_arguments_name_the_valid_values(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Minecraft2DEnv(**kwargs)


def test_out_of_range_actions_raise() -> None:
    env = Minecraft2DEnv()
    env.reset(seed=0)
    for bad in (15, -3, 2.5):
        with pytest.raises(ValueError, match=r"\[0, 14\]"):
            env.step(bad)


# ---------------------------------------------------------------- technology tree


def test_sources_need_their_tools_and_counts_stop_at_their_caps() -> None:
    env = Minecraft2DEnv()
    inv = {i: env.layout[f"inventory.{i}"] for i in ITEMS}
    gather = env.action_index("gather", "stone")
    assert env.transition(_facing(env, "stone"), gather)[0][inv["stone"]] == 0
    assert env.transition(_facing(env, "stone", wood_pickaxe=1), gather)[0][inv["stone"]] == 1
    full = _facing(env, "tree", wood=MAX_COUNT)
    assert env.transition(full, env.action_index("gather", "tree"))[0][inv["wood"]] == MAX_COUNT
    away = _facing(env, "tree", iron_pickaxe=1)
    assert env.transition(away, env.action_index("gather", "diamond"))[0][inv["diamond"]] == 0


def test_crafting_consumes_ingredients_at_the_right_station_once_per_tool() -> None:
    env = Minecraft2DEnv()
    inv = {i: env.layout[f"inventory.{i}"] for i in ITEMS}
    craft = env.action_index("craft", "wood_pickaxe")
    nxt, graph = env.transition(_facing(env, "workbench", wood=2, stick=1), craft)
    assert (nxt[inv["wood"]], nxt[inv["stick"]], nxt[inv["wood_pickaxe"]]) == (1, 0, 1)
    assert {"inventory.stick -> inventory.wood", "inventory.wood -> inventory.stick",
            "inventory.wood_pickaxe -> inventory.wood", "action -> inventory.wood"} <= edge_names(env, graph)
    again = env.transition(_facing(env, "workbench", wood=2, stick=1, wood_pickaxe=1), craft)[0]
    assert again[inv["wood"]] == 2 and again[inv["stick"]] == 1
    smelt = env.action_index("craft", "iron")
    assert env.transition(_facing(env, "workbench", wood=1, iron_ore=1), smelt)[0][inv["iron"]] == 0
    nxt = env.transition(_facing(env, "furnace", wood=1, iron_ore=1), smelt)[0]
    assert (nxt[inv["iron"]], nxt[inv["iron_ore"]], nxt[inv["wood"]]) == (1, 0, 0)


@pytest.mark.parametrize("goal", ["stick", "stone_pickaxe", "diamond"])
def test_scripted_policy_reaches_the_goal_on_unseen_seeds(goal: str) -> None:
    env = Minecraft2DEnv(goal=goal)
    for seed in range(1000, 1050):
        _, infos, success = _play(env, seed)
        assert success and infos[-1]["stages"] == env.stage_names
        counts = [i["num_stages"] for i in infos]
        assert counts == sorted(counts) and counts[-1] == len(env.stage_names)


def test_random_primitives_rarely_get_far_along_the_tree() -> None:
    env = Minecraft2DEnv()
    policy = RandomPrimitivePolicy(env.action_space, seed=0)
    env.reset(seed=0)
    finals = []
    for _ in range(3000):
        _, _, terminated, truncated, info = env.step(int(policy.act(None)[0]))
        if terminated or truncated:
            finals.append(info["num_stages"])
            env.reset()
    assert finals and 0 < np.mean(finals) < len(env.stage_names) / 2


# ---------------------------------------------------------------- true local graphs


def test_local_graphs_are_exactly_what_interventions_find() -> None:
    """(a) changing a non-parent never changes the child; (b) every edge has a change that does."""
    env, rng = Minecraft2DEnv(), np.random.default_rng(5)
    states = _play(env, 0)[0] + [random_box_state(env, rng) for _ in range(40)]
    edges = 0
    for state in states:
        action = int(rng.integers(env.action_space.n))
        graph, intervened = env.transition(state, action)[1], intervened_graph(env, state, action)
        assert not edge_names(env, intervened & ~graph), f"non-parent changes a child: {env.action_names[action]}"
        assert not edge_names(env, graph & ~intervened), f"edge with no effect: {env.action_names[action]}"
        edges += len(edge_names(env, graph))
    assert edges > 100


def test_global_graph_is_the_union_of_local_graphs() -> None:
    assert_global_graph_is_the_union(Minecraft2DEnv(), np.random.default_rng(0))
