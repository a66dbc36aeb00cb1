"""The Chemical environment of CDL (dissertation chapter 3.3.1, modified from Ke et al. 2021).

N objects, each with a colour (one of ``num_colors``) and an (x, y) position. An action sets one
object's colour; every descendant of that object in the object DAG is then re-sampled from its
conditional probability table (a fixed random MLP) given its parents' newest colours. Positions
are fresh Gaussian noise each step and depend on nothing.

The chapter re-samples descendants "in breadth-first order". We use the topological order of the
DAG (Kahn, smallest index first) restricted to the descendants: on collider, chain and full graphs
the two coincide (both are increasing index order), and on any DAG the topological order is the
one in which every parent that will be re-sampled this step is re-sampled *before* its children,
so "the parent's newest colour" is well defined (a breadth-first order can visit a child before
a deeper parent of it).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from envs import chemical_truth
from envs.chemical_cpt import ChemicalCPT
from envs.graphs import ObjectDAG, load_dag
from proto.messages import EnvSpec

POSITION_BOUND = 1e6
"""Observation-space bound on positions (check_env warns on infinite bounds)."""


class ChemicalEnv(gym.Env[np.ndarray, np.int64]):
    """Chemical: N coloured objects whose colours propagate along an object DAG.

    Observation: float32 ``[3N]``, per object ``[colour index, x, y]`` (factors ``obj{k}.color``,
    ``obj{k}.x``, ``obj{k}.y``). Action: ``Discrete(N * num_colors)``, action ``a`` sets object
    ``a // num_colors`` to colour ``a % num_colors``. Reward 0 (tasks come later); episodes never
    terminate and truncate after ``episode_length`` steps. ``info["local_graph"]`` is the uint8
    ``[3N, 3N + 1]`` graph of the transition; :attr:`global_graph` the one-step ground truth.

    ``graph`` is ``"collider"``, ``"chain"``, ``"full"``, a JSON file path or an
    :class:`ObjectDAG`; a file or DAG that states its own number of objects wins over
    ``num_objects``. Positions are drawn i.i.d. from N(0, position_std^2) every step, or from
    N(0, ood_noise_scale^2) when ``ood_noise_scale`` is set (out-of-distribution evaluation).
    ``cpt_seed`` fixes the tables (identical across workers); episodes are seeded by ``reset``.
    """

    metadata = {"render_modes": ["ansi"]}

    def __init__(
        self,
        *,
        graph: str | Path | ObjectDAG = "full",
        num_objects: int = 10,
        num_colors: int = 5,
        episode_length: int = 50,
        position_std: float = 0.01,
        ood_noise_scale: float | None = None,
        cpt_seed: int = 0,
        render_mode: str | None = None,
    ) -> None:
        _check_config(num_colors, episode_length, position_std, ood_noise_scale, render_mode)
        self.dag = graph if isinstance(graph, ObjectDAG) else load_dag(graph, num_objects)
        self.num_objects = n = self.dag.num_objects
        self.num_colors, self.episode_length = num_colors, episode_length
        self.position_std, self.ood_noise_scale = position_std, ood_noise_scale
        self.cpt_seed, self.render_mode = cpt_seed, render_mode
        self.cpt = ChemicalCPT(self.dag, num_colors, cpt_seed)
        self._noise_scale = position_std if ood_noise_scale is None else ood_noise_scale
        self.action_space = gym.spaces.Discrete(n * num_colors)
        self.observation_space = self._make_observation_space()
        self._global_graph = chemical_truth.global_graph(self.dag)
        self._global_graph.flags.writeable = False
        self._local_graphs = tuple(chemical_truth.local_graph(self.dag, i) for i in range(n))
        self._colors: list[int] = [0] * n
        self._positions = np.zeros((n, 2))
        self._steps = 0

    @property
    def global_graph(self) -> np.ndarray:
        """uint8 ``[3N, 3N + 1]`` one-step ground truth (read-only), derived from the dynamics."""
        return self._global_graph

    @property
    def factor_names(self) -> tuple[str, ...]:
        """``obj{k}.color``, ``obj{k}.x``, ``obj{k}.y`` for every object, in observation order."""
        return tuple(f"obj{k}.{f}" for k in range(self.num_objects) for f in ("color", "x", "y"))

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Uniformly random colours, fresh positions. ``reset(seed=s)`` fixes the whole episode."""
        super().reset(seed=seed)
        self._colors = self.np_random.integers(0, self.num_colors, size=self.num_objects).tolist()
        self._positions = self._draw_positions((self.num_objects, 2))
        self._steps = 0
        return self._observation(), {}

    def step(self, action: int | np.integer) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Set one object's colour, re-sample its descendants, redraw every position."""
        target, color = self._decode(action)
        self._positions = self._draw_positions((self.num_objects, 2))
        self.cpt.intervene_one(self._colors, target, color, self.np_random)
        self._steps += 1
        info = {"local_graph": self._local_graphs[target].copy()}
        return self._observation(), 0.0, False, self._steps >= self.episode_length, info

    def sample_next_states(self, states: np.ndarray, action: int) -> np.ndarray:
        """The batched simulator: one step of ``action`` from each row of ``states`` (float
        ``[B, 3N]``), drawing from ``self.np_random`` exactly as :meth:`step` does (a batch of one
        from the current state with the same generator state gives :meth:`step`'s observation).
        The environment's own state and step count are left untouched."""
        colors = self._colors_of(np.asarray(states, dtype=np.float64))
        target, color = self._decode(action)
        positions = self._draw_positions((len(colors), self.num_objects, 2))
        self.cpt.intervene(colors, target, color, self.np_random)
        return self._pack(colors, positions)

    def set_state(self, obs: np.ndarray) -> None:
        """Put the environment in the state of observation ``obs`` (float ``[3N]``)."""
        obs = np.asarray(obs, dtype=np.float64)
        self._colors = self._colors_of(obs[None])[0].tolist()
        self._positions = obs.reshape(self.num_objects, 3)[:, 1:].copy()

    def render(self) -> str | None:
        """``ansi``: the step count and the colour indices as one line of text."""
        if self.render_mode != "ansi":
            return None
        return f"step {self._steps}: colors {self._colors}"

    def env_spec(self) -> EnvSpec:
        """The factor layout, action space, ground truth and configuration, as the bus carries it.

        Not named ``spec``: ``gymnasium.Env.spec`` is the registration record that ``gym.make``,
        wrappers and ``check_env`` read.
        """
        n, c = self.num_objects, self.num_colors
        return EnvSpec(
            env_id="chemical",
            factor_names=self.factor_names,
            factor_kinds=("categorical", "continuous", "continuous") * n,
            factor_sizes=(c, 1, 1) * n,
            factor_objects=tuple(f"obj{k}" for k in range(n) for _ in range(3)),
            factor_locs=(0.0,) * (3 * n),
            factor_scales=(1.0, self.position_std, self.position_std) * n,
            action_kind="categorical",
            action_size=n * c,
            episode_length=self.episode_length,
            global_graph=self._global_graph.copy(),
            config_json=json.dumps(self.config()),
        )

    def config(self) -> dict[str, Any]:
        """The constructor arguments, with the graph as its edge list (JSON-ready)."""
        return {
            "edges": self.dag.to_dict()["edges"],
            "num_objects": self.num_objects,
            "num_colors": self.num_colors,
            "episode_length": self.episode_length,
            "position_std": self.position_std,
            "ood_noise_scale": self.ood_noise_scale,
            "cpt_seed": self.cpt_seed,
        }

    def _make_observation_space(self) -> gym.spaces.Box:
        # A finite bound (check_env warns on infinite ones) 10^4 noise standard deviations wide.
        bound = max(POSITION_BOUND, 1e4 * self._noise_scale)
        low = np.tile([0.0, -bound, -bound], self.num_objects).astype(np.float32)
        high = np.tile([self.num_colors - 1.0, bound, bound], self.num_objects).astype(np.float32)
        return gym.spaces.Box(low, high, dtype=np.float32)

    def _decode(self, action: int | np.integer) -> tuple[int, int]:
        a = int(action)
        if not 0 <= a < self.num_objects * self.num_colors:
            raise ValueError(f"action {a} outside [0, {self.num_objects * self.num_colors - 1}]")
        return divmod(a, self.num_colors)

    def _draw_positions(self, shape: tuple[int, ...]) -> np.ndarray:
        return self.np_random.normal(0.0, self._noise_scale, size=shape)

    def _colors_of(self, states: np.ndarray) -> np.ndarray:
        if states.ndim != 2 or states.shape[1] != 3 * self.num_objects:
            raise ValueError(f"states must have shape (B, {3 * self.num_objects}), got {states.shape}")
        raw = states[:, 0::3]
        colors = raw.astype(np.int64)
        if np.any(colors != raw) or np.any(colors < 0) or np.any(colors >= self.num_colors):
            raise ValueError(f"colours must be integers in [0, {self.num_colors - 1}], got {raw}")
        return colors

    def _pack(self, colors: np.ndarray | list[int], positions: np.ndarray) -> np.ndarray:
        out = np.empty(positions.shape[:-1] + (3,), dtype=np.float32)
        out[..., 0] = colors
        out[..., 1:] = positions
        return out.reshape(positions.shape[:-2] + (-1,))

    def _observation(self) -> np.ndarray:
        return self._pack(self._colors, self._positions)


def _check_config(
    num_colors: int, episode_length: int, position_std: float, ood_noise_scale: float | None, render_mode: str | None
) -> None:
    if num_colors < 2:
        raise ValueError(f"num_colors must be >= 2, got {num_colors}")
    if episode_length < 1:
        raise ValueError(f"episode_length must be >= 1, got {episode_length}")
    if not position_std > 0:
        raise ValueError(f"position_std must be > 0, got {position_std}")
    if ood_noise_scale is not None and not ood_noise_scale > 0:
        raise ValueError(f"ood_noise_scale must be > 0 or None, got {ood_noise_scale}")
    if render_mode not in (None, *ChemicalEnv.metadata["render_modes"]):
        modes = ChemicalEnv.metadata["render_modes"]
        raise ValueError(f"render_mode must be None or one of {modes}, got {render_mode!r}")
