"""The household tasks' cell-by-cell action mode (``action_mode="grid"``, registry names ``<env>-grid``):
Mini-BEHAVIOR's left / right / forward and the object actions in front, the same factors as the
primitive mode, true local graphs checked by hand and against the simulator by interventions."""
from __future__ import annotations

import json
import warnings
from functools import lru_cache

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from envs.household import CleaningCarEnv, InstallingPrinterEnv, ThawingEnv
from envs.household.core import GridTaskEnv
from envs.household.grid import EAST, NORTH, SOUTH, WEST
from envs.registry import env_entry, make_env
from tests.envs.intervention import (assert_global_graph_is_the_union, assert_steps_match_transition, edge_names,
                                     intervened_graph, random_box_state)

ENVS = {"installing-printer": InstallingPrinterEnv, "thawing": ThawingEnv, "cleaning-car": CleaningCarEnv}


def _printer(**values: int) -> tuple[InstallingPrinterEnv, np.ndarray]:
    """Installing Printer in grid mode at a hand-made state: table at (2, 2) (cells x 2-4, y 2-3),
    printer on the floor at (6, 6), agent at (1, 1) facing east; ``values`` override factors."""
    env = InstallingPrinterEnv(action_mode="grid")
    state = {"agent.x": 1, "agent.y": 1, "agent.dir": EAST, "table.x": 2, "table.y": 2, "table.clean": 1,
             "printer.x": 6, "printer.y": 6, "printer.held": 0, "printer.on": 0, "printer.on_table": 0,
             "printer.ready": 0}
    state.update(values)
    return env, np.array([state[n] for n in env.factor_names], dtype=np.float32)


def _into(env: GridTaskEnv, obs: np.ndarray, action: str) -> tuple[dict[str, int], set[str]]:
    """The next state by factor name and the non-self edges of ``action`` (``left``, ``pick(printer)``)."""
    nxt, graph = env.transition(obs, env.action_names.index(action if "(" in action else f"{action}(agent)"))
    return dict(zip(env.factor_names, nxt.astype(int).tolist())), edge_names(env, graph)


@pytest.mark.parametrize("name", ENVS)
def test_grid_mode_keeps_the_factors_and_swaps_goto_for_left_right_forward(name: str) -> None:
    primitives, grid = ENVS[name](), ENVS[name](action_mode="grid")
    a, b = primitives.env_spec(), grid.env_spec()
    for field in ("factor_names", "factor_kinds", "factor_sizes", "factor_objects", "factor_locs", "factor_scales",
                  "episode_length"):
        assert getattr(a, field) == getattr(b, field), field
    assert primitives.observation_space == grid.observation_space
    kept = tuple(n for n in primitives.action_names if not n.startswith("goTo("))
    assert grid.action_names == ("left(agent)", "right(agent)", "forward(agent)", *kept)
    assert b.action_size == grid.action_space.n == len(kept) + 3
    assert (a.env_id, b.env_id) == (name, f"{name}-grid")
    # The same layout at reset in both modes (the mode changes the actions only).
    np.testing.assert_array_equal(primitives.reset(seed=4)[0], grid.reset(seed=4)[0])


@pytest.mark.parametrize("name", ENVS)
def test_registry_entry_builds_the_grid_mode_and_its_config_rebuilds_it(name: str) -> None:
    env = make_env(f"{name}-grid")
    assert env.action_mode == "grid" and env.env_id == f"{name}-grid"
    config = json.loads(env.env_spec().config_json)
    assert config["action_mode"] == "grid"
    assert env_entry(f"{name}-grid").make(**config).action_names == env.action_names
    assert "action_mode" not in json.loads(make_env(name).env_spec().config_json)
    gym_id = env_entry(f"{name}-grid").gym_id
    assert gym.make(gym_id).unwrapped.action_names == env.action_names
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(make_env(f"{name}-grid"), skip_render_check=True)


def test_an_unknown_action_mode_names_the_valid_ones() -> None:
    with pytest.raises(ValueError, match="primitives"):
        InstallingPrinterEnv(action_mode="teleport")


def test_turning_changes_only_the_direction_through_the_action() -> None:
    env, obs = _printer(**{"agent.dir": EAST})
    left, edges = _into(env, obs, "left")
    assert left["agent.dir"] == NORTH and (left["agent.x"], left["agent.y"]) == (1, 1)
    # forward would have moved the agent east: the action is a parent of x too (but-for).
    assert edges == {"action -> agent.dir", "action -> agent.x"}
    right, edges = _into(env, obs, "right")
    assert right["agent.dir"] == SOUTH and edges == {"action -> agent.dir", "action -> agent.x"}
    # Facing the north wall, forward would not move it: the action is a parent of the direction only.
    env, obs = _printer(**{"agent.dir": NORTH})
    assert _into(env, obs, "left")[1] == {"action -> agent.dir"}


def test_forward_moves_one_cell_unless_wall_or_furniture_is_in_front() -> None:
    # Free cell in front: the agent moves east; its new x depends on x, dir, the action, and the table
    # (at another corner the table could cover (2, 1)).
    env, obs = _printer(**{"agent.dir": EAST})
    moved, edges = _into(env, obs, "forward")
    assert (moved["agent.x"], moved["agent.y"]) == (2, 1)
    assert {"agent.dir -> agent.x", "action -> agent.x", "table.y -> agent.x"} <= edges
    assert {e for e in edges if e.endswith("-> agent.y")} == {"agent.dir -> agent.y"}  # facing south it moves
    # A wall in front: nothing moves, and the action changes nothing (no action edge).
    env, obs = _printer(**{"agent.dir": NORTH})
    stay, edges = _into(env, obs, "forward")
    assert (stay["agent.x"], stay["agent.y"]) == (1, 1)
    assert "action -> agent.y" not in edges and "action -> agent.x" not in edges
    assert "agent.dir -> agent.y" in edges  # facing south it would have moved
    # The table in front (agent at (2, 1) facing south, table cell (2, 2)): blocked, through the table.
    env, obs = _printer(**{"agent.x": 2, "agent.y": 1, "agent.dir": SOUTH})
    stay, edges = _into(env, obs, "forward")
    assert (stay["agent.x"], stay["agent.y"]) == (2, 1)
    assert {"table.x -> agent.y", "table.y -> agent.y", "agent.dir -> agent.x"} <= edges
    assert "agent.dir -> agent.y" not in edges  # no other direction changes y here (north is wall)
    assert "action -> agent.y" not in edges
    # An item does not block: the printer at (6, 5), agent at (6, 4) facing south walks onto it.
    env, obs = _printer(**{"agent.x": 6, "agent.y": 4, "agent.dir": SOUTH, "printer.x": 6, "printer.y": 5})
    onto, edges = _into(env, obs, "forward")
    assert (onto["agent.x"], onto["agent.y"]) == (6, 5)
    assert not any(e.startswith("printer.") for e in edges)


def test_object_actions_act_on_the_faced_cell_with_the_primitive_edges() -> None:
    # Printer in front (agent (5, 6) facing east, printer (6, 6)): pick takes it.
    env, obs = _printer(**{"agent.x": 5, "agent.y": 6, "agent.dir": EAST})
    picked, edges = _into(env, obs, "pick(printer)")
    assert picked["printer.held"] == 1
    assert {e for e in edges if e.endswith("-> printer.held")} == {
        f"{p} -> printer.held" for p in ("agent.x", "agent.y", "agent.dir", "printer.x", "printer.y", "action")}
    # Facing away: pick does nothing and the action is no parent of the printer.
    env, obs = _printer(**{"agent.x": 5, "agent.y": 6, "agent.dir": WEST})
    missed, edges = _into(env, obs, "pick(printer)")
    assert missed["printer.held"] == 0 and "action -> printer.held" not in edges
    # Held printer placed on the table cell in front (agent (3, 4) facing north, table cell (3, 3)).
    env, obs = _printer(**{"agent.x": 3, "agent.y": 4, "agent.dir": NORTH, "printer.held": 1})
    placed, edges = _into(env, obs, "place(printer)")
    assert (placed["printer.x"], placed["printer.y"], placed["printer.held"]) == (3, 3, 0)
    assert {"agent.y -> printer.y", "agent.dir -> printer.y", "printer.held -> printer.y", "action -> printer.y"} <= edges
    # Toggle of a printer in front switches it on through agent, printer and action.
    env, obs = _printer(**{"agent.x": 5, "agent.y": 6, "agent.dir": EAST})
    on, edges = _into(env, obs, "toggle(printer)")
    assert on["printer.on"] == 1
    assert {"agent.x -> printer.on", "printer.x -> printer.on", "action -> printer.on"} <= edges


def test_a_grid_mode_episode_installs_the_printer_cell_by_cell() -> None:
    """Walk to the printer, pick it, walk to the table, place, toggle: success and the four stages."""
    env, obs = _printer(**{"agent.x": 6, "agent.y": 2, "agent.dir": SOUTH, "printer.x": 6, "printer.y": 4})
    env.reset(seed=0)
    env.set_state(obs)
    # (6, 2) facing south -> (6, 3); pick the printer at (6, 4); turn west; -> (5, 3); the next
    # forward is blocked by the table cell (4, 3), which the agent then faces: place there, switch on,
    # and one more step for ``ready`` (object states update from the state before the action).
    plan = ["forward", "pick(printer)", "right", "forward", "forward", "place(printer)", "toggle(printer)", "left"]
    infos = []
    for step in plan:
        name = step if "(" in step else f"{step}(agent)"
        obs, reward, terminated, _, info = env.step(env.action_names.index(name))
        infos.append(info)
    lay = env.layout
    assert (obs[lay["printer.x"]], obs[lay["printer.y"]]) == (4, 3)
    assert terminated and reward == 1.0 and infos[-1]["stages"] == env.stage_names


@lru_cache(maxsize=None)
def _checked(name: str) -> tuple[tuple[GridTaskEnv, np.ndarray, int, np.ndarray, np.ndarray], ...]:
    """(env, state, action, the env's graph, the intervened one): random-action and random-box states."""
    env, rng = make_env(f"{name}-grid"), np.random.default_rng(3)
    obs, _ = env.reset(seed=3)
    states = []
    for _ in range(60):
        states.append(obs)
        obs, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        if terminated or truncated:
            obs, _ = env.reset()
    states += [random_box_state(env, rng) for _ in range(40)]
    out = []
    for state in states:
        # Half the checks on the movement actions (the new rules), half on any action.
        action = int(rng.integers(3)) if rng.random() < 0.5 else int(rng.integers(env.action_space.n))
        out.append((env, state, action, env.transition(state, action)[1], intervened_graph(env, state, action)))
    return tuple(out)


@pytest.mark.parametrize("name", ENVS)
def test_grid_mode_local_graphs_match_interventions(name: str) -> None:
    seen = 0
    for env, state, action, graph, intervened in _checked(name):
        assert not edge_names(env, intervened & ~graph), f"{env.action_names[action]} from {state}: missed"
        assert not edge_names(env, graph & ~intervened), f"{env.action_names[action]} from {state}: spurious"
        seen += len(edge_names(env, graph))
    assert seen > 100


@pytest.mark.parametrize("name", ENVS)
def test_grid_mode_step_matches_transition_and_the_global_graph(name: str) -> None:
    env, rng = make_env(f"{name}-grid"), np.random.default_rng(0)
    assert_steps_match_transition(env, rng)
    assert_global_graph_is_the_union(env, rng)


def test_random_actions_rarely_install_the_printer_in_grid_mode() -> None:
    """The point of the mode: uniformly random primitives succeed in ~99% of 150-step episodes,
    uniformly random grid actions in about 1% (3 of 300 measured); 100 seeded episodes here."""
    rates = {}
    for name in ("installing-printer", "installing-printer-grid"):
        env, rng, wins = make_env(name), np.random.default_rng(0), 0
        for episode in range(100):
            env.reset(seed=500 + episode)
            while True:
                _, _, terminated, truncated, info = env.step(int(rng.integers(env.action_space.n)))
                if terminated or truncated:
                    break
            wins += info["success"]
        rates[name] = wins / 100
    assert rates["installing-printer"] >= 0.9 and rates["installing-printer-grid"] <= 0.1, rates
