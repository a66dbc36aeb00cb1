"""A small multi-agent grid world drawn as RGB frames: FLAM's MultiGrid (chapter 8, section 8.3).

``num_agents`` agents (distinct colours) on a ``grid_size`` x ``grid_size`` grid, each moving by its
own action (0 stay, 1 up, 2 down, 3 left, 4 right). Agents are solid: they move one after another
(agent 0 first), and a move off the grid or onto a cell another agent holds at that moment is
blocked (the agent stays). The frame is ``cell_pixels`` pixels per cell, agents drawn as filled
squares of their palette colour on a black background, so the renderer knows each pixel's agent
exactly (``info["masks"]``). Written here rather than depending on the ``multigrid`` package
(docs/deviations.md): the chapter's use of MultiGrid is only agents moving on a grid.

The step takes the joint action as one categorical (``Discrete(5 ** N)``, agent ``i``'s action is
base-5 digit ``i``, agent 0 the least significant) so the env fits the bus's single categorical
action. ``correlated=True`` is the correlated variant of section 8.3: agent 1 repeats agent 0's
action whatever the joint action says, so only ``N - 1`` independent actions remain (K = 3 for 4
agents). ``info["agent_actions"]`` always holds the actions the agents took.
"""
from __future__ import annotations

import json
from typing import Any

import gymnasium as gym
import numpy as np

from envs.chemical_pixels import PALETTE
from proto.messages import EnvSpec

MOVES = np.array([(0, 0), (0, -1), (0, 1), (-1, 0), (1, 0)], dtype=np.int64)
"""(dx, dy) of actions stay, up, down, left, right (y grows downwards, as in the frame)."""
NUM_MOVES = len(MOVES)


class MultiGridAgentsEnv(gym.Env[np.ndarray, int]):
    """Agents on a grid, observed as positions (float ``[2N]``: x, y per agent) and drawn as frames.

    ``reset``/``step`` ``info``: ``frame`` (uint8 ``[H, W, 3]``), ``masks`` (bool ``[N + 1, H, W]``:
    channel 0 the background, ``1 + i`` agent ``i``; they partition the frame) and, after a step,
    ``agent_actions`` (int ``[N]``). Reward-free; episodes truncate after ``episode_length`` steps.
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, *, num_agents: int = 4, grid_size: int = 8, cell_pixels: int = 4,
                 episode_length: int = 50, correlated: bool = False, render_mode: str | None = None) -> None:
        if not 1 <= num_agents <= min(len(PALETTE), grid_size * grid_size):
            raise ValueError(f"num_agents must be in 1..{min(len(PALETTE), grid_size * grid_size)}, got {num_agents}")
        if grid_size < 2 or cell_pixels < 1 or episode_length < 1:
            raise ValueError("grid_size must be >= 2, cell_pixels and episode_length >= 1")
        if correlated and num_agents < 2:
            raise ValueError("the correlated variant needs at least 2 agents")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.num_agents, self.grid_size, self.cell_pixels = num_agents, grid_size, cell_pixels
        self.episode_length, self.correlated, self.render_mode = episode_length, correlated, render_mode
        self.frame_size = grid_size * cell_pixels
        self.observation_space = gym.spaces.Box(0.0, grid_size - 1.0, shape=(2 * num_agents,), dtype=np.float32)
        self.action_space = gym.spaces.Discrete(NUM_MOVES ** num_agents)
        self._positions = np.zeros((num_agents, 2), dtype=np.int64)
        self._t = 0

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Agents on distinct uniformly random cells."""
        super().reset(seed=seed)
        cells = self.np_random.permutation(self.grid_size ** 2)[: self.num_agents]
        self._positions = np.stack([cells % self.grid_size, cells // self.grid_size], axis=1)
        self._t = 0
        return self._observation(), self._frame_info()

    def step(self, action: int | np.integer) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move every agent by its digit of the joint ``action`` (agent 1 copies agent 0 if correlated)."""
        if not self.action_space.contains(int(action)):
            raise ValueError(f"action must be in 0..{self.action_space.n - 1}, got {action}")
        actions = self.agent_actions(int(action))
        self._positions = self.transition(self._positions, actions)
        self._t += 1
        info = {**self._frame_info(), "agent_actions": actions}
        return self._observation(), 0.0, False, self._t >= self.episode_length, info

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        """``rgb_array``: the current frame (uint8 ``[H, W, 3]``)."""
        return self.render_positions(self._positions[None])[0][0] if self.render_mode == "rgb_array" else None

    def agent_actions(self, joint: int) -> np.ndarray:
        """int ``[N]``: the agents' actions a joint action gives (agent 1 = agent 0 when correlated)."""
        actions = (joint // NUM_MOVES ** np.arange(self.num_agents)) % NUM_MOVES
        if self.correlated:
            actions[1] = actions[0]
        return actions

    def joint_action(self, actions: np.ndarray) -> int:
        """The joint action whose digits are ``actions`` (int ``[N]``)."""
        return int((np.asarray(actions) * NUM_MOVES ** np.arange(self.num_agents)).sum())

    def transition(self, positions: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """Next positions (int ``[N, 2]``): agents move in order; off-grid or occupied targets block."""
        positions = positions.copy()
        for i in range(self.num_agents):
            target = positions[i] + MOVES[actions[i]]
            inside = bool(((target >= 0) & (target < self.grid_size)).all())
            free = not (np.delete(positions, i, axis=0) == target).all(axis=1).any()
            if inside and free:
                positions[i] = target
        return positions

    def render_positions(self, positions: np.ndarray,
                         goals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Frames uint8 ``[B, H, W, 3]`` and labels uint8 ``[B, H, W]`` (0 background, ``1 + i`` agent
        ``i``) of a batch of positions (int ``[B, N, 2]``), vectorised over the batch. ``goals`` (int
        ``[B, 2]``, the goal task's) draws a goal cell under the agents: label ``N + 1``, colour
        ``PALETTE[N]``."""
        positions = np.asarray(positions, dtype=np.int64)
        cells = np.zeros((len(positions), self.grid_size, self.grid_size), dtype=np.uint8)
        if goals is not None:
            goals = np.asarray(goals, dtype=np.int64)
            cells[np.arange(len(positions)), goals[:, 1], goals[:, 0]] = self.num_agents + 1
        batch = np.repeat(np.arange(len(positions)), self.num_agents)
        agents = np.tile(np.arange(self.num_agents), len(positions))
        flat = positions.reshape(-1, 2)
        cells[batch, flat[:, 1], flat[:, 0]] = agents + 1
        labels = cells.repeat(self.cell_pixels, axis=1).repeat(self.cell_pixels, axis=2)
        rgb = np.concatenate([np.zeros((1, 3), np.uint8), PALETTE[: self.num_agents + 1]])
        return rgb[labels], labels

    def env_spec(self) -> EnvSpec:
        """Positions as categorical factors (x and y per agent), the joint action as one categorical."""
        n = 2 * self.num_agents
        return EnvSpec(
            env_id="multigrid-agents-correlated" if self.correlated else "multigrid-agents",
            factor_names=tuple(f"agent{i}.{axis}" for i in range(self.num_agents) for axis in "xy"),
            factor_kinds=("categorical",) * n, factor_sizes=(self.grid_size,) * n,
            factor_objects=tuple(f"agent{i}" for i in range(self.num_agents) for _ in "xy"),
            factor_locs=(0.0,) * n, factor_scales=(1.0,) * n,
            action_kind="categorical", action_size=int(self.action_space.n),
            episode_length=self.episode_length, config_json=json.dumps(self.config()))

    def config(self) -> dict[str, Any]:
        return {"num_agents": self.num_agents, "grid_size": self.grid_size, "cell_pixels": self.cell_pixels,
                "episode_length": self.episode_length, "correlated": self.correlated}

    def _observation(self) -> np.ndarray:
        return self._positions.reshape(-1).astype(np.float32)

    def _frame_info(self) -> dict[str, np.ndarray]:
        frames, labels = self.render_positions(self._positions[None])
        masks = labels[0][None] == np.arange(self.num_agents + 1)[:, None, None]
        return {"frame": frames[0], "masks": masks}


class CorrelatedMultiGridAgentsEnv(MultiGridAgentsEnv):
    """The correlated variant (section 8.3): agent 1 always takes agent 0's action."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**{"correlated": True, **kwargs})


class MultiGridGoalEnv(MultiGridAgentsEnv):
    """Table 8.4's task on MultiGrid (our stand-in for the chapter's Procgen games; docs/deviations.md):
    the player, agent 0, collects goals while the other agents wander.

    The action (``Discrete(5)``) moves the player; the other agents take uniformly random moves from
    the env's generator (so a seeded reset fixes the episode given the player's actions), after the
    player, as in :meth:`transition`. A goal cell (drawn under the agents, colour ``PALETTE[N]``) lies on
    a cell no agent holds; the player stepping onto it earns reward 1 and a new goal appears on a free
    cell. Episodes truncate after ``episode_length`` steps; the return is the number of goals
    collected. Observation: the agents' positions then the goal's (float ``[2N + 2]``); ``info`` as
    the parent's with ``masks`` ``[N + 2, H, W]`` (channel ``N + 1`` the goal where no agent covers it),
    ``agent_actions``, ``goals`` (collected so far) and ``success`` (at least one). :func:`goal_expert_action` is the scripted
    expert. Not a ``--env`` of the registry: the behaviour-cloning benchmark (``benchmarks.flam_bc
    --env multigrid``) is its one user."""

    def __init__(self, *, num_agents: int = 4, grid_size: int = 8, cell_pixels: int = 4,
                 episode_length: int = 50, render_mode: str | None = None) -> None:
        if num_agents >= len(PALETTE):
            raise ValueError(f"num_agents must be at most {len(PALETTE) - 1} (the goal takes a colour), got {num_agents}")
        super().__init__(num_agents=num_agents, grid_size=grid_size, cell_pixels=cell_pixels,
                         episode_length=episode_length, render_mode=render_mode)
        if num_agents >= grid_size * grid_size:
            raise ValueError("the goal needs a cell no agent holds: num_agents < grid_size ** 2")
        self.action_space = gym.spaces.Discrete(NUM_MOVES)
        self.observation_space = gym.spaces.Box(0.0, grid_size - 1.0, shape=(2 * num_agents + 2,), dtype=np.float32)
        self.goal = np.zeros(2, dtype=np.int64)
        self.collected = 0

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.collected = 0
        self._place_goal()
        return self._observation(), self._frame_info()

    def step(self, action: int | np.integer) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self.action_space.contains(int(action)):
            raise ValueError(f"action must be in 0..{NUM_MOVES - 1}, got {action}")
        actions = np.concatenate([[int(action)], self.np_random.integers(NUM_MOVES, size=self.num_agents - 1)])
        self._positions = self.transition(self._positions, actions)
        self._t += 1
        reward = 0.0
        if (self._positions[0] == self.goal).all():
            reward, self.collected = 1.0, self.collected + 1
            self._place_goal()
        info = {**self._frame_info(), "agent_actions": actions, "goals": self.collected, "success": self.collected > 0}
        return self._observation(), reward, False, self._t >= self.episode_length, info

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        return self.render_scene()[0] if self.render_mode == "rgb_array" else None

    def render_scene(self) -> tuple[np.ndarray, np.ndarray]:
        """The current frame (uint8 ``[H, W, 3]``) and its labels (uint8 ``[H, W]``, goal ``N + 1``)."""
        frames, labels = self.render_positions(self._positions[None], self.goal[None])
        return frames[0], labels[0]

    def env_spec(self) -> EnvSpec:
        """The agents' positions then the goal's as categorical factors; the player's move as the action."""
        n = 2 * self.num_agents + 2
        objects = [f"agent{i}" for i in range(self.num_agents)] + ["goal"]
        return EnvSpec(
            env_id="multigrid-goal", factor_names=tuple(f"{o}.{axis}" for o in objects for axis in "xy"),
            factor_kinds=("categorical",) * n, factor_sizes=(self.grid_size,) * n,
            factor_objects=tuple(o for o in objects for _ in "xy"), factor_locs=(0.0,) * n,
            factor_scales=(1.0,) * n, action_kind="categorical", action_size=NUM_MOVES,
            episode_length=self.episode_length, config_json=json.dumps(self.config()))

    def config(self) -> dict[str, Any]:
        return {key: value for key, value in super().config().items() if key != "correlated"}

    def _place_goal(self) -> None:
        held = set(map(tuple, self._positions.tolist()))
        free = [cell for cell in range(self.grid_size ** 2) if (cell % self.grid_size, cell // self.grid_size) not in held]
        cell = free[int(self.np_random.integers(len(free)))]
        self.goal = np.array([cell % self.grid_size, cell // self.grid_size], dtype=np.int64)

    def _observation(self) -> np.ndarray:
        return np.concatenate([self._positions.reshape(-1), self.goal]).astype(np.float32)

    def _frame_info(self) -> dict[str, np.ndarray]:
        frame, labels = self.render_scene()
        return {"frame": frame, "masks": labels[None] == np.arange(self.num_agents + 2)[:, None, None]}


def goal_expert_action(env: MultiGridGoalEnv) -> int:
    """The goal task's scripted expert (Table 8.4's expert; the chapter trains one with PPG): the move
    toward the goal along the axis with the larger distance (x on ties), or along the other axis when
    another agent holds that cell; the first of them when both are held (the move is blocked). Never
    stays. Deterministic; reads the true positions."""
    player, goal = env._positions[0], env.goal
    delta = goal - player
    order = (0, 1) if abs(delta[0]) >= abs(delta[1]) else (1, 0)
    moves = [_toward(axis, delta[axis]) for axis in order if delta[axis] != 0]
    others = env._positions[1:]
    for move in moves:
        if not (others == player + MOVES[move]).all(axis=1).any():
            return move
    return moves[0]


def _toward(axis: int, delta: int) -> int:
    """The move along ``axis`` (0 x, 1 y) in the sign of ``delta``."""
    return (4 if delta > 0 else 3) if axis == 0 else (2 if delta > 0 else 1)


def displacement_codes(positions: np.ndarray) -> np.ndarray:
    """Each agent's observed move between consecutive frames, one-hot over the 9 cell offsets in
    ``{-1, 0, 1}^2``: float ``[E * T, N, 9]`` from ``positions`` int ``[E, T + 1, N, 2]``.

    The best codes a latent action can be, made from what the frames show: an agent whose move is
    blocked (by the wall or another agent) shows the same offset as one that stays, so these codes
    score below 1 against the actions the agents took. DCI of these codes against the actions is
    the ceiling of the latent actions' (``dci_*_ceiling`` of FLAM's scores)."""
    positions = np.asarray(positions)
    delta = np.diff(positions, axis=1).reshape(-1, positions.shape[2], 2)
    if np.abs(delta).max(initial=0) > 1:
        raise ValueError("positions move more than one cell per step")
    index = (delta[..., 0] + 1) * 3 + (delta[..., 1] + 1)
    return np.eye(9, dtype=np.float32)[index]


def record_videos(env: MultiGridAgentsEnv, episodes: int, steps: int, seed: int) -> dict[str, np.ndarray]:
    """Action-free videos from a uniformly random policy, with the truth kept for scoring.

    Returns ``frames`` uint8 ``[E, T + 1, H, W, 3]``, ``labels`` uint8 ``[E, T + 1, H, W]`` (each
    pixel's agent, 0 background), ``positions`` int ``[E, T + 1, N, 2]`` and ``actions`` int
    ``[E, T, N]`` (the actions the agents took). Episode ``e`` resets with seed ``seed + e`` and
    draws its actions from ``numpy.random.default_rng((seed, e))``."""
    positions = np.zeros((episodes, steps + 1, env.num_agents, 2), dtype=np.int64)
    actions = np.zeros((episodes, steps, env.num_agents), dtype=np.int64)
    for e in range(episodes):
        env.reset(seed=seed + e)
        rng = np.random.default_rng((seed, e))
        positions[e, 0] = env._positions
        for t in range(steps):
            actions[e, t] = env.agent_actions(int(rng.integers(env.action_space.n)))
            positions[e, t + 1] = env.transition(positions[e, t], actions[e, t])
    frames, labels = env.render_positions(positions.reshape(-1, env.num_agents, 2))
    shape = (episodes, steps + 1) + frames.shape[1:3]
    return {"frames": frames.reshape(shape + (3,)), "labels": labels.reshape(shape),
            "positions": positions, "actions": actions}
