"""The household tasks (Installing Printer, Thawing, Cleaning Car): gymnasium contract, seeding,
layout and spec, the rules, stages, scripted and random policies, and the true local graphs checked
against the simulator by interventions (:mod:`tests.envs.intervention`)."""
from __future__ import annotations

import json
import warnings
from functools import lru_cache
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.utils.passive_env_checker import env_render_passive_checker

from envs.household import CleaningCarEnv, InstallingPrinterEnv, ThawingEnv
from envs.household.cleaning_car import TASKS as CAR_TASKS
from envs.household.core import GridTaskEnv
from envs.household.scripted import RandomPrimitivePolicy, scripted_policy
from envs.household.thawing import TASKS as THAW_TASKS
from proto.codec import decode, encode
from proto.messages import EnvSpec
from tests.envs.intervention import (assert_global_graph_is_the_union, assert_steps_match_transition, edge_names,
                                     intervened_graph, random_box_state)

ENVS = {"installing-printer": InstallingPrinterEnv, "thawing": ThawingEnv, "cleaning-car": CleaningCarEnv}
CONFIGS = [("installing-printer", {})] + [("thawing", {"task": t}) for t in THAW_TASKS] + [
    ("cleaning-car", {"task": t}) for t in CAR_TASKS] + [("cleaning-car", {"episode_length": 300})]


def _make(name: str, **kwargs: Any) -> GridTaskEnv:
    return ENVS[name](**kwargs)


def _rollout(env: GridTaskEnv, seed: int, actions: list[int]) -> tuple[np.ndarray, ...]:
    obs, _ = env.reset(seed=seed)
    observations, rewards, graphs, stages = [obs], [], [], []
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        observations.append(obs)
        rewards.append(reward)
        graphs.append(info["local_graph"])
        stages.append(info["num_stages"])
        if terminated or truncated:
            obs, _ = env.reset()
            observations.append(obs)
    return np.array(observations), np.array(rewards), np.array(graphs), np.array(stages)


def _play(env: GridTaskEnv, seed: int, policy: Any = None) -> tuple[list[np.ndarray], list[dict], bool]:
    """One episode (scripted by default): observations before each step, infos, success."""
    policy = policy or scripted_policy(env)
    obs, _ = env.reset(seed=seed)
    policy.reset()
    observations, infos = [], []
    while True:
        observations.append(obs)
        obs, _, terminated, truncated, info = env.step(int(policy.act(obs)[0]))
        infos.append(info)
        if terminated or truncated:
            return observations, infos, terminated


# ---------------------------------------------------------------- gymnasium contract and seeding


@pytest.mark.parametrize(("name", "kwargs"), CONFIGS)
def test_check_env_passes_without_warnings(name: str, kwargs: dict) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(_make(name, **kwargs), skip_render_check=True)
        env = _make(name, render_mode="ansi", **kwargs)
        env.reset(seed=0)
        env_render_passive_checker(env)
    assert "#" in env.render()


@pytest.mark.parametrize("name", ENVS)
def test_gymnasium_make_builds_it_from_its_entry_point_and_kwargs(name: str) -> None:
    """As a registry would: ``gym.make`` with the constructor's keyword arguments, render modes
    checked too (they need a spec), and the scripted policy through the wrappers."""
    cls = ENVS[name]
    env_id = f"causeway-test/{cls.__name__}-v0"
    if env_id not in gym.registry:
        gym.register(env_id, entry_point=f"{cls.__module__}:{cls.__name__}")
    env = gym.make(env_id, room_size=9, episode_length=200)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    assert json.loads(env.unwrapped.env_spec().config_json)["room_size"] == 9
    policy, (obs, _) = scripted_policy(env), env.reset(seed=0)
    for _ in range(200):
        obs, _, terminated, _, _ = env.step(int(policy.act(obs)[0]))
        if terminated:
            break
    assert terminated


@pytest.mark.parametrize("name", ENVS)
def test_reset_seed_makes_the_episode_reproducible(name: str) -> None:
    env = _make(name)
    actions = np.random.default_rng(0).integers(env.action_space.n, size=400).tolist()
    first, second, other = _rollout(env, 7, actions), _rollout(_make(name), 7, actions), _rollout(env, 8, actions)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first[0][:50], other[0][:50])


@pytest.mark.parametrize("name", ENVS)
def test_layout_spaces_and_spec(name: str) -> None:
    env = _make(name)
    d = len(env.factor_names)
    spec = env.env_spec()
    assert env.observation_space.shape == (d,) and env.action_space.n == len(env.action_names)
    assert spec.factor_names == env.factor_names and spec.factor_kinds == ("categorical",) * d
    assert spec.factor_sizes == tuple(int(h) + 1 for h in env.observation_space.high)
    assert spec.factor_objects == tuple(n.split(".")[0] for n in env.factor_names)
    assert spec.factor_locs == (0.0,) * d and spec.factor_scales == (1.0,) * d
    assert (spec.action_kind, spec.action_size, spec.state_dim) == ("categorical", env.action_space.n, d)
    np.testing.assert_array_equal(spec.global_graph, env.global_graph)
    assert spec.global_graph.shape == (d, d + 1) and np.all(np.diag(spec.global_graph) == 1)
    decoded = decode(encode(spec), EnvSpec)
    assert decoded.factor_names == spec.factor_names and decoded.config_json == spec.config_json
    rebuilt = ENVS[name](**json.loads(spec.config_json)).env_spec()
    assert rebuilt.config_json == spec.config_json and rebuilt.factor_sizes == spec.factor_sizes
    assert env.factor_names[:3] == ("agent.x", "agent.y", "agent.dir")


def test_factor_lists_and_actions_are_the_chapters() -> None:
    printer, thawing, car = InstallingPrinterEnv(), ThawingEnv(), CleaningCarEnv()
    assert printer.factor_names[3:] == ("table.x", "table.y", "table.clean", "printer.x", "printer.y", "printer.held",
                                        "printer.on", "printer.on_table", "printer.ready")
    assert {"fridge.open", "sink.on", "fish.frozen", "olive.frozen", "date.frozen"} <= set(thawing.factor_names)
    assert {"car.stained", "bucket.soaped", "rag.soak", "rag.dirty", "soap.held"} <= set(car.factor_names)
    assert (len(printer.factor_names), len(thawing.factor_names), len(car.factor_names)) == (12, 21, 20)
    assert (printer.action_space.n, thawing.action_space.n, car.action_space.n) == (5, 14, 10)
    assert printer.action_names == ("goTo(table)", "goTo(printer)", "pick(printer)", "place(printer)",
                                    "toggle(printer)")
    assert printer.constant_factors() == ("table.clean",)
    assert (printer.layout.room_size, printer.episode_length) == (8, 150)
    assert (thawing.layout.room_size, thawing.episode_length, car.episode_length) == (10, 300, 100)


@pytest.mark.parametrize("name", ENVS)
def test_episodes_truncate_at_the_step_limit(name: str) -> None:
    env = _make(name, episode_length=3)
    env.reset(seed=0)
    flags = [env.step(0)[2:4] for _ in range(3)]  # goTo(a piece of furniture)
    assert flags == [(False, False), (False, False), (False, True)]


# ---------------------------------------------------------------- arguments and actions


@pytest.mark.parametrize(("name", "kwargs", "message"), [
    ("thawing", {"task": "thaw-peach"}, "'thaw-fish', 'thaw-olive', 'thaw-date', 'thaw-all'"),
    ("cleaning-car", {"task": "wash-car"}, "'soak-rag', 'clean-car', 'clean-rag'"),
    ("thawing", {"room_size": 6}, r"room_size must be an integer in \[7, 32\]"),
    ("cleaning-car", {"room_size": 6}, r"room_size must be an integer in \[7, 32\]"),
    ("installing-printer", {"room_size": 33}, r"\[6, 32\]"),
    ("installing-printer", {"room_size": 8.5}, r"\[6, 32\]"),
    ("installing-printer", {"episode_length": 0}, "episode_length must be an integer >= 1"),
    ("installing-printer", {"render_mode": "human"}, "render_mode must be None or one of"),
])
def test_bad_constructor_arguments_name_the_valid_values(name: str, kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        _make(name, **kwargs)


@pytest.mark.parametrize("name", ENVS)
def test_out_of_range_actions_raise(name: str) -> None:
    env = _make(name)
    obs, _ = env.reset(seed=0)
    n = env.action_space.n
    for bad in (-1, n, 1.5, "pick"):
        with pytest.raises(ValueError, match=rf"action .*\[0, {n - 1}\]"):
            env.step(bad)
    with pytest.raises(ValueError, match="outside"):
        env.transition(obs, n)
    with pytest.raises(KeyError, match="no action fly"):
        env.action_index("fly", "sink")


def test_set_state_validates_and_snapshots_restore() -> None:
    env = ThawingEnv()
    obs, _ = env.reset(seed=3)
    snapshot = env.snapshot()
    bad = obs.copy()
    bad[env.layout["fish.frozen"]] = 6
    with pytest.raises(ValueError, match=r"fish.frozen=6.0 not in \[0, 5\]"):
        env.set_state(bad)
    with pytest.raises(ValueError, match="21 factors"):
        env.set_state(obs[:5])
    half = obs.copy()
    half[0] = 1.5
    with pytest.raises(ValueError, match="agent.x"):
        env.set_state(half)
    after = env.step(0)[0]
    np.testing.assert_array_equal(env.restore(snapshot), obs)
    np.testing.assert_array_equal(env.step(0)[0], after)


# ---------------------------------------------------------------- rules


def _thawing_with(**values: int) -> tuple[ThawingEnv, np.ndarray]:
    """A Thawing room with the fridge at (1, 1), the sink at (5, 5) and ``values`` set."""
    env = ThawingEnv()
    obs, _ = env.reset(seed=0)
    base = {"fridge.x": 1, "fridge.y": 1, "sink.x": 5, "sink.y": 5, "fridge.open": 0, "sink.on": 0,
            "olive.x": 8, "olive.y": 8, "date.x": 8, "date.y": 8, **values}
    for name, v in base.items():
        obs[env.layout[name]] = v
    env.set_state(obs)
    return env, obs


def test_thawing_rules_and_the_closed_fridge() -> None:
    # The fish lies on the sink's corner, the agent below it facing north; the sink is off.
    env, obs = _thawing_with(**{"fish.x": 5, "fish.y": 6, "fish.frozen": 5, "agent.x": 5, "agent.y": 7,
                                "agent.dir": 3})
    toggle, pick = env.action_index("toggle", "sink"), env.action_index("pick", "fish")
    levels = [env.step(toggle if t == 0 else env.action_index("goTo", "sink"))[0][env.layout["fish.frozen"]]
              for t in range(7)]
    assert levels == [5, 4, 3, 2, 1, 0, 0]  # states update before the action: the step after 'on'
    # In the closed fridge the fish cannot be picked, and it refreezes.
    env, obs = _thawing_with(**{"fish.x": 1, "fish.y": 1, "fish.frozen": 3, "agent.x": 1, "agent.y": 2,
                                "agent.dir": 3})
    nxt, _, _, _, info = env.step(pick)
    assert nxt[env.layout["fish.held"]] == 0 and nxt[env.layout["fish.frozen"]] == 4
    assert "fridge.open -> fish.held" in edge_names(env, info["local_graph"])


def test_picking_the_fish_has_the_expected_local_graph() -> None:
    env, obs = _thawing_with(**{"fish.x": 1, "fish.y": 1, "fish.frozen": 5, "agent.x": 1, "agent.y": 2,
                                "agent.dir": 3, "fridge.open": 1})
    nxt, graph = env.transition(obs, env.action_index("pick", "fish"))
    assert nxt[env.layout["fish.held"]] == 1
    held = {e for e in edge_names(env, graph) if e.endswith("-> fish.held")}
    assert held == {f"{p} -> fish.held" for p in ("agent.x", "agent.y", "agent.dir", "fish.x", "fish.y",
                                                   "fridge.open", "action")}
    # The fish stays frozen in the fridge whatever the sink does, unless the sink could cover it.
    frozen = {e for e in edge_names(env, graph) if e.endswith("-> fish.frozen")}
    assert frozen == set()


def test_cleaning_car_chain_follows_the_rules() -> None:
    env = CleaningCarEnv(task="clean-rag")
    observations, infos, success = _play(env, seed=5)
    lay = env.layout
    soak = [o[lay["rag.soak"]] for o in observations]
    assert success and all(b - a in (0, 1) for a, b in zip(soak, soak[1:]))
    cleaned = [o[lay["car.stained"]] for o in observations].index(0)
    assert observations[cleaned][lay["rag.dirty"]] == 5 and observations[cleaned - 1][lay["rag.soak"]] == 5
    dirty = [o[lay["rag.dirty"]] for o in observations[cleaned:]]
    assert dirty[:1] == [5] and all(b - a in (0, -1) for a, b in zip(dirty, dirty[1:]))
    assert infos[-1]["stages"] == env.stage_names and infos[-1]["success"]


def test_printer_is_ready_when_on_and_on_the_clean_table() -> None:
    env = InstallingPrinterEnv()
    observations, infos, success = _play(env, seed=2)
    lay = env.layout
    ready = [o[lay["printer.ready"]] for o in observations]
    assert success and not any(ready)  # success ends the episode on the first ready step
    last = observations[-1]
    assert last[lay["printer.on"]] == 1 and last[lay["printer.on_table"]] == 1 and last[lay["table.clean"]] == 1
    assert infos[-1]["stages"] == ("pick printer", "printer on table", "turn on printer", "install printer")


# ---------------------------------------------------------------- stages and policies


@pytest.mark.parametrize(("name", "kwargs"), CONFIGS)
def test_scripted_policy_succeeds_on_unseen_seeds(name: str, kwargs: dict) -> None:
    env = _make(name, **kwargs)
    results = [_play(env, seed) for seed in range(1000, 1050)]
    assert all(success for _, _, success in results)
    for _, infos, _ in results:
        assert infos[-1]["stages"] == env.stage_names and infos[-1]["num_stages"] == len(env.stage_names)


@pytest.mark.parametrize("name", ENVS)
def test_stages_are_reported_in_order_and_never_lost(name: str) -> None:
    env = _make(name)
    policy = RandomPrimitivePolicy(env.action_space, seed=0)
    _, info = env.reset(seed=0)
    assert info == {"stages": (), "num_stages": 0}
    previous = ()
    for _ in range(1000):
        _, reward, terminated, truncated, info = env.step(int(policy.act(None)[0]))
        stages = info["stages"]
        assert info["num_stages"] == len(stages) and set(previous) <= set(stages)
        assert list(stages) == [s for s in env.stage_names if s in stages]
        assert reward == float(terminated) == float(info["success"])
        assert not terminated or stages[-1] == env.stage_names[-1]
        previous = stages
        if terminated or truncated:
            env.reset()
            previous = ()


def test_random_primitive_policy_is_seeded_and_in_range() -> None:
    env = CleaningCarEnv()
    a, b = RandomPrimitivePolicy(env.action_space, 3), RandomPrimitivePolicy(env.action_space, 3)
    acts = np.array([a.act(None) for _ in range(200)])
    assert acts.dtype == np.float32 and acts.shape == (200, 1)
    np.testing.assert_array_equal(acts, [b.act(None) for _ in range(200)])
    assert set(acts[:, 0].astype(int)) == set(range(env.action_space.n))


# ---------------------------------------------------------------- true local graphs


@lru_cache(maxsize=None)
def _checked_transitions(name: str) -> tuple[tuple[GridTaskEnv, np.ndarray, int, np.ndarray, np.ndarray], ...]:
    """(env, state, action, the env's local graph, the intervened one) for states a random policy
    and the scripted policy visit and uniformly random states of the observation box."""
    env, rng = _make(name), np.random.default_rng(11)
    states = [o for seed in range(2) for o in _play(env, seed)[0]]
    states += _play(env, 9, RandomPrimitivePolicy(env.action_space, 9))[0][:40]
    states += [random_box_state(env, rng) for _ in range(40)]
    out = []
    for state in states:
        action = int(rng.integers(env.action_space.n))
        out.append((env, state, action, env.transition(state, action)[1], intervened_graph(env, state, action)))
    return tuple(out)


@pytest.mark.parametrize("name", ENVS)
def test_changing_a_non_parent_never_changes_the_child(name: str) -> None:
    for env, state, action, graph, intervened in _checked_transitions(name):
        missed = edge_names(env, intervened & ~graph)
        assert not missed, f"{env.action_names[action]} from {state}: changes through non-parents {missed}"


@pytest.mark.parametrize("name", ENVS)
def test_every_edge_has_a_change_of_the_parent_that_changes_the_child(name: str) -> None:
    seen = 0
    for env, state, action, graph, intervened in _checked_transitions(name):
        spurious = edge_names(env, graph & ~intervened)
        assert not spurious, f"{env.action_names[action]} from {state}: no change through {spurious}"
        seen += len(edge_names(env, graph))
    assert seen > 100


@pytest.mark.parametrize("name", ENVS)
def test_step_gives_the_same_graph_as_transition_and_the_global_graph_is_their_union(name: str) -> None:
    env, rng = _make(name), np.random.default_rng(0)
    assert_steps_match_transition(env, rng)
    assert_global_graph_is_the_union(env, rng)


@pytest.mark.parametrize("name", ["thawing", "cleaning-car"])
def test_labels_are_sparse_under_random_primitives(name: str) -> None:
    """Chapter 5: at most 3% of the labels are positive (off-diagonal, action column included)."""
    env = _make(name)
    _, _, graphs, _ = _rollout(env, 0, np.random.default_rng(0).integers(env.action_space.n, size=3000).tolist())
    d = graphs.shape[1]
    assert (graphs.sum() - graphs.shape[0] * d) / (graphs.shape[0] * d * d) < 0.03
