"""Chemical Match (dissertation ch. 3.3.5): make every object's colour match a goal colour.

The goal is the colours reached by a sequence of random interventions on a copy of the start state
(the reference's construction), so it is reachable under the same dynamics. The dense reward is
the fraction of objects whose colour matches. The goal colours are provided to the agent as extra
factors ``obj{k}.goal_color`` appended to the observation (the chapter's "provided extra factors"):
they are constant within an episode and depend only on themselves.
"""
from __future__ import annotations

import dataclasses
import json
from typing import Any

import gymnasium as gym
import numpy as np

from envs.chemical import ChemicalEnv
from proto.messages import EnvSpec


class ChemicalMatchEnv(ChemicalEnv):
    """Chemical with the Match task: observation ``[3N + N]`` = Chemical's ``[colour, x, y]`` per
    object, then the N goal colours; reward = fraction of objects at their goal colour after the
    step. Every :class:`ChemicalEnv` option passes through (``ood_noise_scale`` included).

    ``goal_interventions`` random actions build the goal (default: one per object).
    """

    def __init__(self, *, goal_interventions: int | None = None, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.goal_interventions = self.num_objects if goal_interventions is None else goal_interventions
        if self.goal_interventions < 1:
            raise ValueError(f"goal_interventions must be >= 1, got {self.goal_interventions}")
        self._goal = np.zeros(self.num_objects, dtype=np.int64)
        self._global_graph = with_goal_factors(self._global_graph, self.num_objects)
        self._global_graph.flags.writeable = False
        self._local_graphs = tuple(with_goal_factors(g, self.num_objects) for g in self._local_graphs)

    @property
    def goal_colors(self) -> np.ndarray:
        """The current episode's goal colours (int ``[N]``, a copy)."""
        return self._goal.copy()

    @property
    def factor_names(self) -> tuple[str, ...]:
        """Chemical's factors, then ``obj{k}.goal_color``."""
        return super().factor_names + tuple(f"obj{k}.goal_color" for k in range(self.num_objects))

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Chemical's reset, then a goal from ``goal_interventions`` random interventions on a copy."""
        _, info = super().reset(seed=seed, options=options)
        self._goal = self._intervened_copy()
        return self._observation(), info

    def step(self, action: int | np.integer) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Chemical's step; the reward is the fraction of objects matching the goal."""
        obs, _, terminated, truncated, info = super().step(action)
        return obs, float(self.match_fraction(obs)), terminated, truncated, info

    def match_fraction(self, obs: np.ndarray) -> np.floating | np.ndarray:
        """Fraction of objects at their goal colour, for observations ``[..., 4N]``."""
        obs = np.asarray(obs)
        n = self.num_objects
        return np.mean(obs[..., 0 : 3 * n : 3] == obs[..., 3 * n :], axis=-1)

    def sample_next_states(self, states: np.ndarray, action: int) -> np.ndarray:
        """Chemical's batched simulator on Match observations ``[B, 4N]`` (goals carried through)."""
        states = np.asarray(states)
        nxt = super().sample_next_states(states[:, : 3 * self.num_objects], action)
        return np.concatenate([nxt, states[:, 3 * self.num_objects :].astype(np.float32)], axis=1)

    def set_state(self, obs: np.ndarray) -> None:
        """Put the environment (goal included) in the state of observation ``obs`` (``[4N]``)."""
        obs = np.asarray(obs, dtype=np.float64)
        n = self.num_objects
        if obs.shape != (4 * n,):
            raise ValueError(f"Match observations have shape ({4 * n},), got {obs.shape}")
        goal = obs[3 * n :]
        if np.any(goal != np.round(goal)) or np.any(goal < 0) or np.any(goal >= self.num_colors):
            raise ValueError(f"goal colours must be integers in [0, {self.num_colors - 1}], got {goal}")
        super().set_state(obs[: 3 * n])
        self._goal = goal.astype(np.int64)

    def env_spec(self) -> EnvSpec:
        """Chemical's spec with the goal colours as extra categorical factors and self-edges."""
        spec = super().env_spec()
        n, c = self.num_objects, self.num_colors
        return dataclasses.replace(
            spec, env_id="chemical-match", factor_names=self.factor_names,
            factor_kinds=spec.factor_kinds + ("categorical",) * n, factor_sizes=spec.factor_sizes + (c,) * n,
            factor_objects=spec.factor_objects + tuple(f"obj{k}" for k in range(n)),
            factor_locs=spec.factor_locs + (0.0,) * n, factor_scales=spec.factor_scales + (1.0,) * n,
            config_json=json.dumps(self.config()),
        )

    def config(self) -> dict[str, Any]:
        """Chemical's configuration plus ``goal_interventions``."""
        return {**super().config(), "goal_interventions": self.goal_interventions}

    def _make_observation_space(self) -> gym.spaces.Box:
        chemical = super()._make_observation_space()
        low = np.concatenate([chemical.low, np.zeros(self.num_objects, np.float32)])
        high = np.concatenate([chemical.high, np.full(self.num_objects, self.num_colors - 1.0, np.float32)])
        return gym.spaces.Box(low, high, dtype=np.float32)

    def _observation(self) -> np.ndarray:
        return np.concatenate([super()._observation(), self._goal.astype(np.float32)])

    def _intervened_copy(self) -> np.ndarray:
        colors = np.array([self._colors], dtype=np.int64)
        for _ in range(self.goal_interventions):
            target, color = divmod(int(self.np_random.integers(self.action_space.n)), self.num_colors)
            self.cpt.intervene(colors, target, color, self.np_random)
        return colors[0]


def with_goal_factors(graph: np.ndarray, num_objects: int) -> np.ndarray:
    """A Chemical graph ``[3N, 3N + 1]`` extended to ``[4N, 4N + 1]``: goal factors keep only their self-edges."""
    n_state = graph.shape[0]
    size = n_state + num_objects
    out = np.zeros((size, size + 1), dtype=graph.dtype)
    out[:n_state, :n_state] = graph[:, :n_state]
    out[:n_state, size] = graph[:, n_state]
    out[np.arange(n_state, size), np.arange(n_state, size)] = 1
    return out
