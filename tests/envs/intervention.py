"""Interventions on a grid task's simulator (household tasks, 2D Minecraft): the local graph found
by changing one thing at a time, which the environments' own local graphs are checked against.

``s^i_t -> s^j_{t+1}`` is found when some other value of factor ``i`` alone (every value of the
observation box, the action and everything else kept; the dynamics have no random draws) changes
``s^j_{t+1}``; ``a_t -> s^j_{t+1}`` when some other action changes it.
"""
from __future__ import annotations

import numpy as np

from envs.household.core import GridTaskEnv


def intervened_graph(env: GridTaskEnv, state: np.ndarray, action: int) -> np.ndarray:
    """uint8 ``[d, d + 1]``: the parents of each next factor found by single-factor interventions."""
    nxt, _ = env.transition(state, action)
    d = len(state)
    graph = np.zeros((d, d + 1), dtype=np.uint8)
    graph[np.arange(d), np.arange(d)] = 1
    low = env.observation_space.low.astype(int)
    high = env.observation_space.high.astype(int)
    for i in range(d):
        for v in range(low[i], high[i] + 1):
            if v != state[i]:
                changed = state.copy()
                changed[i] = v
                graph[:, i] |= env.transition(changed, action)[0] != nxt
    for b in range(env.action_space.n):
        graph[:, d] |= env.transition(state, b)[0] != nxt
    return graph


def random_box_state(env: GridTaskEnv, rng: np.random.Generator) -> np.ndarray:
    """A uniformly random point of the observation box (every one is a valid state)."""
    low, high = env.observation_space.low.astype(int), env.observation_space.high.astype(int)
    return rng.integers(low, high + 1).astype(np.float32)


def edge_names(env: GridTaskEnv, graph: np.ndarray) -> set[str]:
    """``"parent -> child"`` for every non-self edge of ``graph``."""
    columns = (*env.factor_names, "action")
    return {f"{columns[i]} -> {env.factor_names[j]}" for j, i in zip(*np.nonzero(graph)) if i != j}


def assert_steps_match_transition(env: GridTaskEnv, rng: np.random.Generator, steps: int = 50) -> None:
    """``env.step`` gives ``env.transition``'s next state and local graph (uint8) for ``steps`` random actions."""
    obs, _ = env.reset(seed=0)
    for a in rng.integers(env.action_space.n, size=steps):
        expected = env.transition(obs, a)
        obs, _, terminated, truncated, info = env.step(a)
        np.testing.assert_array_equal(obs, expected[0])
        np.testing.assert_array_equal(info["local_graph"], expected[1])
        assert info["local_graph"].dtype == np.uint8
        if terminated or truncated:
            obs, _ = env.reset()


def assert_global_graph_is_the_union(env: GridTaskEnv, rng: np.random.Generator, tries: int = 3000) -> None:
    """The union of the local graphs of every action from random box states is the global graph."""
    union = np.zeros_like(env.global_graph)
    for _ in range(tries):
        state = random_box_state(env, rng)
        for a in range(env.action_space.n):
            union |= env.transition(state, a)[1]
        if np.array_equal(union, env.global_graph):
            break
    assert edge_names(env, union ^ env.global_graph) == set()
