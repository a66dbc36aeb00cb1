"""The gymnasium environment every grid task (household and 2D Minecraft) is an instance of.

A task gives its objects (a :class:`~envs.household.grid.Layout`), its actions (primitives on
objects, :mod:`envs.household.primitives`), its object-state updates (:class:`~envs.household.rules.Rule`),
its semantic stages (chapter 5, Fig 5.4), the last of which is success, and how it lays out a room
at reset (a function of a numpy generator). This class does the rest: the gymnasium API, the local graphs, the stages in ``info``,
interventions (:meth:`GridTaskEnv.set_state`, :meth:`GridTaskEnv.transition`) and the bus's
:class:`~proto.messages.EnvSpec`.

Reward is sparse: +1 on the step that reaches success, which ends the episode (``terminated``),
0 otherwise. (The authors' Mini-BEHAVIOR code pays -1 per step until success; chapter 5 pays a
sparse reward on success only, and its curves count stages; +1 on success has the same optimal
policies within the step limit and keeps returns in [0, 1].) Episodes truncate after
``episode_length`` steps.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Sequence

import gymnasium as gym
import numpy as np

from envs.household.grid import DX, DY, Layout, check_episode_length
from envs.household.primitives import Action, grid_actions
from envs.household.rules import Rule, RuleEngine
from proto.messages import EnvSpec


@dataclass(frozen=True)
class Stage:
    """A semantic stage toward success: reached once ``reached(state)`` has held at some step."""

    name: str
    reached: Callable[[list[int]], bool]


@dataclass(frozen=True)
class Snapshot:
    """An episode's whole state: the factors, the step count and the stages reached so far."""

    state: tuple[int, ...]
    steps: int
    reached: tuple[bool, ...]


class GridTaskEnv(gym.Env[np.ndarray, np.int64]):
    """A task in a grid room, with factored categorical observations and true local graphs.

    Observation: float32 ``[d_S]`` in the order of :attr:`factor_names`, every factor a category
    index. Action: ``Discrete(len(action_names))``, one primitive on one object each; with
    ``action_mode="grid"`` the ``goTo`` primitives give way to Mini-BEHAVIOR's ``left``, ``right``
    and ``forward`` (:func:`envs.household.primitives.grid_actions`; the factors are the same).
    ``env_id`` is then ``<task env>-grid``, the registry's name of that mode.
    ``info["local_graph"]``: uint8 ``[d_S, d_S + 1]`` (rows: factors at ``t + 1``; columns: factors
    at ``t``, then the action), see :mod:`envs.household.rules`; ``info["stages"]``: names of the
    stages reached so far this episode, in stage order; ``info["num_stages"]``: how many;
    ``info["success"]``: whether the task is done.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["ansi"], "render_fps": 4}
    env_id: ClassVar[str] = ""

    def __init__(self, layout: Layout, actions: Sequence[Action], updates: Sequence[Rule], stages: Sequence[Stage],
                 lay_out: Callable[[np.random.Generator], list[int]], episode_length: int,
                 render_mode: str | None, action_mode: str = "primitives") -> None:
        check_episode_length(episode_length)
        actions = grid_actions(layout, actions, action_mode)
        self.action_mode = action_mode
        if action_mode != "primitives":
            self.env_id = f"{type(self).env_id}-{action_mode}"

        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.layout, self.actions, self.stages = layout, tuple(actions), tuple(stages)
        self._lay_out = lay_out
        self.episode_length, self.render_mode = int(episode_length), render_mode
        d = layout.num_factors
        self.engine = RuleEngine([layout.domain(i) for i in range(d)], updates, [a.rules for a in self.actions])
        self.action_space = gym.spaces.Discrete(len(self.actions))
        self.observation_space = gym.spaces.Box(layout.low, layout.high, dtype=np.float32)
        self._global_graph = self.engine.global_graph()
        self._global_graph.flags.writeable = False
        self._state = [f.low for f in layout.factors]
        self._steps = 0
        self._reached: list[bool] = []
        self._pending: list[int] = []
        self._reached_names: tuple[str, ...] = ()
        self._set_reached([False] * len(self.stages))

    # ------------------------------------------------------------------ task hooks

    def config(self) -> dict[str, Any]:
        """The constructor arguments (JSON-ready)."""
        return {"room_size": self.layout.room_size, "episode_length": self.episode_length, **self._mode_config()}

    def _mode_config(self) -> dict[str, Any]:
        """``action_mode`` for the config, where the env takes it and it is not the default."""
        return {"action_mode": self.action_mode} if self.action_mode != "primitives" else {}

    def constant_factors(self) -> tuple[str, ...]:
        """Factors with the same value in every episode (their edges are true but unlearnable here)."""
        return ()

    # ------------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """A new room; ``reset(seed=s)`` fixes the episode (the dynamics are deterministic)."""
        super().reset(seed=seed)
        self._state = self._lay_out(self.np_random)
        self._steps = 0
        self._set_reached([False] * len(self.stages))
        self._update_stages(self._state)
        return self._observation(), {"stages": self._reached_names, "num_stages": len(self._reached_names)}

    def step(self, action: int | np.integer) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Update object states, apply the primitive, report the local graph and the stages."""
        state, edges = self.engine.step(self._state, self._action_index(action))
        self._state = state
        self._steps += 1
        success = self._update_stages(state)
        info = {"local_graph": self.engine.graph(edges), "stages": self._reached_names,
                "num_stages": len(self._reached_names), "success": success}
        truncated = not success and self._steps >= self.episode_length
        return self._observation(), float(success), success, truncated, info

    def render(self) -> str | None:
        """``ansi``: the room as text (``#`` wall, capitals furniture, lower case items on the floor,
        the agent as ``>v<^``) and the held items."""
        if self.render_mode != "ansi":
            return None
        return _draw(self.layout, self._state)

    # ------------------------------------------------------------------ interventions

    def set_state(self, obs: np.ndarray) -> None:
        """Put the room in the state of observation ``obs`` (ValueError unless valid)."""
        self._state = self.layout.check_state(obs)

    def transition(self, obs: np.ndarray, action: int | np.integer) -> tuple[np.ndarray, np.ndarray]:
        """The next observation and local graph from ``obs`` under ``action``; the environment's own
        state is left untouched (the simulator as a pure function, for interventions)."""
        state, edges = self.engine.step(self.layout.check_state(obs), self._action_index(action))
        return np.array(state, dtype=np.float32), self.engine.graph(edges)

    def snapshot(self) -> Snapshot:
        """The current episode, to :meth:`restore` later."""
        return Snapshot(tuple(self._state), self._steps, tuple(self._reached))

    def restore(self, snapshot: Snapshot) -> np.ndarray:
        """Return to ``snapshot`` and give its observation."""
        self._state, self._steps = list(snapshot.state), snapshot.steps
        self._set_reached(list(snapshot.reached))
        return self._observation()

    # ------------------------------------------------------------------ layout and spec

    @property
    def factor_names(self) -> tuple[str, ...]:
        return self.layout.names

    @property
    def action_names(self) -> tuple[str, ...]:
        """``primitive(object)`` per action index."""
        return tuple(a.name for a in self.actions)

    @property
    def stage_names(self) -> tuple[str, ...]:
        """Every stage of the task, in order; the last one is success."""
        return tuple(s.name for s in self.stages)

    @property
    def global_graph(self) -> np.ndarray:
        """uint8 ``[d_S, d_S + 1]`` (read-only): the union of the local graphs over all states."""
        return self._global_graph

    def action_index(self, primitive: str, target: str) -> int:
        """The action ``primitive(target)``; KeyError naming the actions if there is none."""
        name = f"{primitive}({target})"
        try:
            return self.action_names.index(name)
        except ValueError:
            raise KeyError(f"no action {name}; actions: {self.action_names}") from None

    def env_spec(self) -> EnvSpec:
        """The factor layout, action space, ground truth and configuration, as the bus carries it.
        Every factor is categorical (a category index), so locs are 0 and scales 1."""
        d = self.layout.num_factors
        return EnvSpec(
            env_id=self.env_id,
            factor_names=self.factor_names,
            factor_kinds=("categorical",) * d,
            factor_sizes=self.layout.sizes,
            factor_objects=tuple(f.obj for f in self.layout.factors),
            factor_locs=(0.0,) * d,
            factor_scales=(1.0,) * d,
            action_kind="categorical",
            action_size=len(self.actions),
            episode_length=self.episode_length,
            global_graph=self._global_graph.copy(),
            config_json=json.dumps(self.config()),
        )

    # ------------------------------------------------------------------ internals

    def _observation(self) -> np.ndarray:
        return np.array(self._state, dtype=np.float32)

    def _action_index(self, action: int | np.integer) -> int:
        n = len(self.actions)
        try:
            a = int(action)
        except (TypeError, ValueError):
            raise ValueError(f"action must be an integer in [0, {n - 1}], got {action!r}") from None
        if a != action or not 0 <= a < n:
            raise ValueError(f"action {action!r} outside [0, {n - 1}]: one of the {n} primitives {self.action_names}")
        return a

    def _update_stages(self, state: list[int]) -> bool:
        """Mark the stages reached in ``state``; whether the last one (success) holds now."""
        newly = [k for k in self._pending if self.stages[k].reached(state)]
        if newly:
            self._set_reached([r or k in newly for k, r in enumerate(self._reached)])
        return self._reached[-1] and self.stages[-1].reached(state)

    def _set_reached(self, reached: list[bool]) -> None:
        self._reached = reached
        self._pending = [k for k, r in enumerate(reached) if not r]
        self._reached_names = tuple(s.name for s, r in zip(self.stages, reached) if r)


_ARROWS = ">v<^"


def _draw(layout: Layout, state: list[int]) -> str:
    r = layout.room_size
    rows = [["#"] * r] + [["#"] + ["."] * (r - 2) + ["#"] for _ in range(r - 2)] + [["#"] * r]
    held = []
    for name, spec in layout.objects.items():
        if name == "agent" or not spec.located:
            continue
        x, y = state[layout[f"{name}.x"]], state[layout[f"{name}.y"]]
        if spec.movable and state[layout[f"{name}.held"]]:
            held.append(name)
            continue
        for i in range(spec.width):
            for j in range(spec.height):
                rows[y + j][x + i] = name[0].lower() if spec.movable else name[0].upper()
    ax, ay, d = (state[layout[f"agent.{a}"]] for a in ("x", "y", "dir"))
    rows[ay][ax] = _ARROWS[d]
    front = f"front ({ax + DX[d]}, {ay + DY[d]})"
    return "\n".join("".join(row) for row in rows) + f"\n{front}; held: {', '.join(held) or 'nothing'}"
