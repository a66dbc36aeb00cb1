"""A small sprite game in the spirit of Procgen's bigfish, drawn with exact per-object masks (issue 24).

Written here (Procgen itself does not give per-object masks or factors): the agent fish moves by
its action; ``num_fish`` other fish of varied sizes and colours swim horizontally, each at its own
constant speed, enter at one side of the frame and leave at the other; fish overlap each other and
the agent. If the agent touches a smaller fish it eats it (reward 1) and grows; if it touches a fish
of its size or larger it is eaten and the episode ends; reaching ``WIN_SIZE`` ends it with reward 10
(bigfish's rewards). Frames are ``frame_size`` x ``frame_size`` RGB (32 by default, or 64) over a
textured background (seeded horizontal stripes of blue and per-pixel noise, drawn at every reset).

Every sprite has more than one colour (body in its colour's palette entry, tail and dorsal fin in a
second colour, a white eye with a black pupil), and several fish may share a colour, so colour alone
does not segment the frame. Sprites are painted in a fixed order (fish 1..N, then the agent on top,
painter's algorithm), so each pixel shows exactly one object and ``info["masks"]`` (bool
``[N + 2, H, W]``: channel 0 the background, ``1`` the agent, ``1 + i`` fish ``i``) is each object's
visible, occlusion-aware mask; the channels partition the frame.

Factors (float32 observation, per object in order agent, fish1..fishN): ``x``, ``y`` (frame
coordinates in ``(-1, 1)``, a fish's ``x`` goes beyond them while it enters or leaves), ``vx``
(horizontal speed per step; the agent's is 0), ``size`` (half the body length), ``color`` (palette
index; the agent's is always 0, fish draw 1..num_colors-1) and ``alive`` (0 or 1). A fish that leaves
the frame or is eaten has ``alive`` 0 for one step (its other factors kept, nothing drawn) and is then
respawned at a side of the frame with fresh ``y``, ``vx``, ``size`` and ``color``.

``info["local_graph"]`` (uint8 ``[d_S, d_S + 1]``, row: a factor at t+1, column: a factor at t or the
action, last) is the transition's true local graph: every factor's self-edge; the action into the
agent's ``x`` and ``y``; a living fish's ``x`` from its ``vx``; the leaving of a fish (its ``alive``
from its ``x``, ``vx`` and ``size``); a respawn (each of the fish's factors from its ``alive``); and an
eat event between the agent and fish ``i`` (the contact is decided at the moved positions, so from
the agent's ``x``, ``y``, ``size``, the action and the fish's ``x``, ``y``, ``vx``, ``size``,
``alive``): into the agent's ``size`` and the fish's ``alive`` when the agent eats, into the agent's
``alive`` when it is eaten.
"""
from __future__ import annotations

import json
from typing import Any

import gymnasium as gym
import numpy as np

from envs import demonstrations
from envs.chemical_pixels import PALETTE
from proto.messages import EnvSpec

FIELDS = ("x", "y", "vx", "size", "color", "alive")
"""Per-object factors, in this order."""
X, Y, VX, SIZE, COLOR, ALIVE = range(len(FIELDS))
NUM_FIELDS = len(FIELDS)

MOVES9 = np.array([(0, 0), (0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (1, -1), (-1, 1), (1, 1)], dtype=np.float64)
"""(dx, dy) of the actions: stay, up, down, left, right, then the diagonals (with ``num_moves=9``)."""
AGENT_STEP = 0.08
"""How far one move takes the agent, per axis (frame coordinates)."""
SPEED_RANGE = (0.02, 0.08)
"""A fish's |vx| per step, uniform."""
SIZE_RANGE = (0.08, 0.28)
"""A fish's size (half its body length), uniform."""
AGENT_START_SIZE = 0.14
GROWTH = 0.02
"""How much the agent's size grows per fish eaten."""
WIN_SIZE = 0.32
"""The agent's size that ends the episode with :data:`WIN_REWARD`."""
EAT_REWARD, WIN_REWARD = 1.0, 10.0
HEIGHT = 0.6
"""A body's half-height as a fraction of its size."""
CONTACT = 0.7
"""Bodies touch when their ellipses scaled by this factor overlap (a box test, per axis)."""

FIN_COLORS = np.array([(20, 20, 120), (200, 200, 200), (40, 90, 30), (120, 60, 10), (90, 10, 60),
                       (10, 110, 110), (150, 80, 20), (60, 20, 90), (90, 110, 20), (120, 90, 100)], dtype=np.uint8)
"""Tail and fin colour of palette index ``c`` (differs from the body's)."""
EYE, PUPIL = np.array((255, 255, 255), np.uint8), np.array((0, 0, 0), np.uint8)


class SpritesEnv(gym.Env[np.ndarray, np.int64]):
    """The bigfish-like sprite game (module docstring); observation the factors, frames in ``info``.

    ``reset``/``step`` ``info``: ``frame`` (uint8 ``[H, W, 3]``), ``masks`` (bool ``[N + 2, H, W]``),
    ``local_graph`` after a step, ``eaten`` (the fish the agent ate this step, 1-based, or 0) and
    ``success`` (whether the agent reached the winning size). Episodes end when the agent is eaten or
    wins, and truncate after ``episode_length`` steps.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 15}

    def __init__(self, *, num_fish: int = 4, num_colors: int = 6, num_moves: int = 5, frame_size: int = 32,
                 episode_length: int = 200, render_mode: str | None = None) -> None:
        if not 1 <= num_fish <= 16:
            raise ValueError(f"num_fish must be in 1..16, got {num_fish}")
        if not 2 <= num_colors <= len(PALETTE):
            raise ValueError(f"num_colors must be in 2..{len(PALETTE)} (the agent's colour and at least one), "
                             f"got {num_colors}")
        if num_moves not in (5, 9):
            raise ValueError(f"num_moves must be 5 or 9, got {num_moves}")
        if frame_size not in (32, 64):
            raise ValueError(f"frame_size must be 32 or 64, got {frame_size}")
        if episode_length < 1:
            raise ValueError(f"episode_length must be >= 1, got {episode_length}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.num_fish, self.num_colors, self.num_moves = num_fish, num_colors, num_moves
        self.frame_size, self.episode_length, self.render_mode = frame_size, episode_length, render_mode
        self.num_objects = num_fish + 1
        n = self.num_objects * NUM_FIELDS
        limit = 1.0 + SIZE_RANGE[1] * 1.5 + SPEED_RANGE[1]
        low = np.tile(np.array([-limit, -1.0, -SPEED_RANGE[1], 0.0, 0.0, 0.0], np.float32), self.num_objects)
        high = np.tile(np.array([limit, 1.0, SPEED_RANGE[1], 1.0, num_colors - 1.0, 1.0], np.float32), self.num_objects)
        self.observation_space = gym.spaces.Box(low, high, shape=(n,), dtype=np.float32)
        self.action_space = gym.spaces.Discrete(num_moves)
        self._state = np.zeros((self.num_objects, NUM_FIELDS))
        self._background = np.zeros((frame_size, frame_size, 3), np.uint8)
        self._t = 0

    # -- dynamics ---------------------------------------------------------------------------------

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """A fresh background; the agent at the centre; every fish alive somewhere in the frame."""
        super().reset(seed=seed)
        self._background = self._draw_background()
        state = np.zeros((self.num_objects, NUM_FIELDS))
        state[0] = (0.0, 0.0, 0.0, AGENT_START_SIZE, 0.0, 1.0)
        for i in range(1, self.num_objects):
            state[i] = self._spawn()
            state[i, X] = self.np_random.uniform(-0.9, 0.9)
            # no fish starts touching the agent
            while _touch(state[0], state[i]):
                state[i, X] = self.np_random.uniform(-0.9, 0.9)
        self._state, self._t = state, 0
        return self._observation(), {**self._frame_info(), "eaten": 0, "success": False}

    def step(self, action: int | np.integer) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move the agent and the fish, then resolve leaving, contacts and respawns (module docstring)."""
        if not self.action_space.contains(int(action)):
            raise ValueError(f"action must be in 0..{self.num_moves - 1}, got {action}")
        old = self._state
        new, graph, reward, eaten, dead = self.transition(old, int(action))
        self._state = new
        self._t += 1
        success = bool(new[0, SIZE] >= WIN_SIZE - 1e-9)
        if success:
            reward += WIN_REWARD
        info = {**self._frame_info(), "local_graph": graph, "eaten": eaten, "success": success}
        return self._observation(), reward, dead or success, self._t >= self.episode_length, info

    def transition(self, state: np.ndarray, action: int) -> tuple[np.ndarray, np.ndarray, float, int, bool]:
        """One step from ``state`` (float ``[N + 1, 6]``): the next state, the local graph, the reward,
        the fish eaten (1-based, 0 none) and whether the agent was eaten. Draws respawns from the env's
        generator."""
        new = state.copy()
        graph = np.zeros((self.num_objects * NUM_FIELDS, self.num_objects * NUM_FIELDS + 1), np.uint8)
        graph[np.arange(len(graph)), np.arange(len(graph))] = 1
        f = lambda obj, field: obj * NUM_FIELDS + field  # noqa: E731
        dx, dy = MOVES9[action]
        new[0, X] = np.clip(state[0, X] + dx * AGENT_STEP, -1.0, 1.0)
        new[0, Y] = np.clip(state[0, Y] + dy * AGENT_STEP, -1.0, 1.0)
        graph[[f(0, X), f(0, Y)], -1] = 1
        reward, eaten, dead = 0.0, 0, False
        for i in range(1, self.num_objects):
            if state[i, ALIVE] < 0.5:  # respawn
                new[i] = self._spawn()
                graph[f(i, 0):f(i, NUM_FIELDS), f(i, ALIVE)] = 1
                continue
            new[i, X] = state[i, X] + state[i, VX]
            graph[f(i, X), f(i, VX)] = 1
            if abs(new[i, X]) - new[i, SIZE] * 1.5 > 1.0:  # left the frame
                new[i, ALIVE] = 0.0
                graph[f(i, ALIVE), [f(i, X), f(i, VX), f(i, SIZE)]] = 1
        for i in range(1, self.num_objects):
            if state[i, ALIVE] < 0.5 or new[i, ALIVE] < 0.5 or dead or not _touch(new[0], new[i]):
                continue
            contact = [f(0, X), f(0, Y), f(0, SIZE), f(i, X), f(i, Y), f(i, VX), f(i, SIZE), f(i, ALIVE)]
            if state[0, SIZE] > state[i, SIZE]:
                new[0, SIZE] += GROWTH
                new[i, ALIVE] = 0.0
                for child in (f(0, SIZE), f(i, ALIVE)):
                    graph[child, contact] = 1
                    graph[child, -1] = 1
                reward += EAT_REWARD
                eaten = eaten or i
            else:
                new[0, ALIVE] = 0.0
                graph[f(0, ALIVE), contact] = 1
                graph[f(0, ALIVE), -1] = 1
                dead = True
        return new, graph, reward, eaten, dead

    def _spawn(self) -> np.ndarray:
        """A fresh fish at a side of the frame, swimming inwards."""
        rng = self.np_random
        size = rng.uniform(*SIZE_RANGE)
        direction = 1.0 if rng.random() < 0.5 else -1.0
        return np.array([-direction * (1.0 + size * 1.5), rng.uniform(-0.85, 0.85),
                         direction * rng.uniform(*SPEED_RANGE), size, float(rng.integers(1, self.num_colors)), 1.0])

    # -- rendering --------------------------------------------------------------------------------

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        """``rgb_array``: the current frame (uint8 ``[H, W, 3]``)."""
        return self.render_state(self._state)[0] if self.render_mode == "rgb_array" else None

    def render_state(self, state: np.ndarray, background: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Frame uint8 ``[H, W, 3]`` and labels uint8 ``[H, W]`` (0 background, 1 the agent, ``1 + i``
        fish ``i``) of ``state`` (float ``[N + 1, 6]``) over ``background`` (default: this episode's).
        Painter's order: fish 1..N, then the agent; a later sprite hides an earlier one."""
        frame = (self._background if background is None else background).copy()
        labels = np.zeros(frame.shape[:2], np.uint8)
        for obj in list(range(1, self.num_objects)) + [0]:
            if state[obj, ALIVE] < 0.5:
                continue
            for part, colour in zip(self.sprite_parts(state[obj]), self._part_colours(int(state[obj, COLOR]))):
                frame[part] = colour
                labels[part] = obj + 1
        return frame, labels

    def sprite_parts(self, obj: np.ndarray) -> tuple[np.ndarray, ...]:
        """bool ``[H, W]`` pixel sets of one object's sprite parts, painted in order: body, tail and
        fin, eye, pupil (each over the previous). The sprite's pixels are their union."""
        size = self.frame_size
        pixel = (np.arange(size) + 0.5) * (2.0 / size) - 1.0
        px, py = pixel[None, :], pixel[:, None]
        heading = 1.0 if obj[VX] >= 0 else -1.0
        s, h = obj[SIZE], obj[SIZE] * HEIGHT
        dx, dy = (px - obj[X]) * heading, py - obj[Y]  # dx > 0: ahead of the centre
        body = (dx / s) ** 2 + (dy / h) ** 2 <= 1.0
        back = -dx - 0.7 * s  # distance behind the body's rear
        tail = (back >= 0) & (back <= 0.6 * s) & (np.abs(dy) <= 0.2 * h + back * 1.2)
        fin = (dy <= -0.7 * h) & (dy >= -1.3 * h) & (np.abs(dx + 0.1 * s) <= 0.35 * s * (-0.7 * h - dy) / (0.6 * h))
        eye_r = max(0.22 * h, 1.0 / size)
        eye = (dx - 0.5 * s) ** 2 + (dy + 0.2 * h) ** 2 <= eye_r ** 2
        pupil = (np.abs(dx - 0.55 * s) <= 1.0 / size) & (np.abs(dy + 0.2 * h) <= 1.0 / size) & eye
        return body, tail | fin, eye, pupil

    def _part_colours(self, color: int) -> tuple[np.ndarray, ...]:
        return PALETTE[color], FIN_COLORS[color], EYE, PUPIL

    def _draw_background(self) -> np.ndarray:
        """Seeded horizontal stripes of blues and greens with per-pixel noise."""
        size, rng = self.frame_size, self.np_random
        bands = rng.integers(2, 6)
        edges = np.sort(rng.integers(1, size, size=bands - 1))
        band_of_row = np.searchsorted(edges, np.arange(size), side="right")
        colours = rng.integers((0, 20, 50), (40, 90, 140), size=(bands, 3))
        wave = rng.integers(-2, 3, size=size)  # ripples: each column shifts the stripes a little
        rows = np.clip(np.arange(size)[:, None] + wave[None, :], 0, size - 1)
        image = colours[band_of_row[rows]] + rng.integers(-15, 16, size=(size, size, 3))
        return np.clip(image, 0, 255).astype(np.uint8)

    # -- spec -------------------------------------------------------------------------------------

    def object_names(self) -> tuple[str, ...]:
        return ("agent",) + tuple(f"fish{i}" for i in range(1, self.num_objects))

    def env_spec(self) -> EnvSpec:
        """Continuous x, y, vx, size; categorical colour and alive; the moves as one categorical."""
        kinds = {"x": "continuous", "y": "continuous", "vx": "continuous", "size": "continuous",
                 "color": "categorical", "alive": "categorical"}
        sizes = {"x": 1, "y": 1, "vx": 1, "size": 1, "color": self.num_colors, "alive": 2}
        locs = {"x": 0.0, "y": 0.0, "vx": 0.0, "size": 0.2, "color": 0.0, "alive": 0.0}
        scales = {"x": 0.6, "y": 0.5, "vx": 0.05, "size": 0.06, "color": 1.0, "alive": 1.0}
        names = self.object_names()
        return EnvSpec(
            env_id="sprites",
            factor_names=tuple(f"{o}.{k}" for o in names for k in FIELDS),
            factor_kinds=tuple(kinds[k] for _ in names for k in FIELDS),
            factor_sizes=tuple(sizes[k] for _ in names for k in FIELDS),
            factor_objects=tuple(o for o in names for _ in FIELDS),
            factor_locs=tuple(locs[k] for _ in names for k in FIELDS),
            factor_scales=tuple(scales[k] for _ in names for k in FIELDS),
            action_kind="categorical", action_size=self.num_moves, episode_length=self.episode_length,
            config_json=json.dumps(self.config()),
            state_low=self.observation_space.low.copy(), state_high=self.observation_space.high.copy())

    def config(self) -> dict[str, Any]:
        return {"num_fish": self.num_fish, "num_colors": self.num_colors, "num_moves": self.num_moves,
                "frame_size": self.frame_size, "episode_length": self.episode_length}

    def _observation(self) -> np.ndarray:
        return self._state.reshape(-1).astype(np.float32)

    def _frame_info(self) -> dict[str, np.ndarray]:
        frame, labels = self.render_state(self._state)
        masks = labels[None] == np.arange(self.num_objects + 1)[:, None, None]
        return {"frame": frame, "masks": masks}


def _touch(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two bodies touch: their half-extents scaled by :data:`CONTACT` overlap on both axes."""
    return bool(abs(a[X] - b[X]) < CONTACT * (a[SIZE] + b[SIZE])
                and abs(a[Y] - b[Y]) < CONTACT * HEIGHT * (a[SIZE] + b[SIZE]))


def record_frames(env: SpritesEnv, seed: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` frames (uint8 ``[count, H, W, 3]``) and label maps (uint8 ``[count, H, W]``) of
    uniformly random play: episodes reset with seeds ``seed, seed + 1, ...``, actions from
    ``numpy.random.default_rng(seed)``; every reset's and step's frame is kept."""
    rng = np.random.default_rng(seed)
    frames = np.zeros((count, env.frame_size, env.frame_size, 3), np.uint8)
    labels = np.zeros((count, env.frame_size, env.frame_size), np.uint8)
    episode, done = 0, True
    for t in range(count):
        if done:
            env.reset(seed=seed + episode)
            episode += 1
            done = False
        else:
            _, _, terminated, truncated, _ = env.step(int(rng.integers(env.num_moves)))
            done = terminated or truncated
        frames[t], labels[t] = env.render_state(env._state)
    return frames, labels


def expert_action(state: np.ndarray, num_moves: int = 5) -> int:
    """A scripted expert for the sprite game (Table 8.4's expert; the chapter trains one with PPG):
    the move whose two-step look-ahead scores best on the true state (float ``[N + 1, 6]``).

    Each move is followed by the best second move, the fish swimming on at their speeds (respawns are
    not foreseen). A step touching a living fish at least the agent's size scores -100; eating a smaller
    one +10; otherwise the score is minus the distance to the nearest smaller fish in the frame (where
    the agent will meet it) and a penalty growing as a larger fish comes within 0.5. Ties go to the
    lower move index. Deterministic; no generator."""
    agent, fish = state[0], state[1:][state[1:, ALIVE] > 0.5]

    def fish_at(steps: int) -> np.ndarray:
        moved = fish.copy()
        moved[:, X] += moved[:, VX] * steps
        return moved

    later = (fish_at(1), fish_at(2))

    def score(position: np.ndarray, step: int) -> float:
        body = agent.copy()
        body[X], body[Y] = position
        value = 0.0
        for other in later[step]:
            if abs(other[X]) - other[SIZE] * 1.5 > 1.0:
                continue
            touching = _touch(body, other)
            distance = float(np.hypot(body[X] - other[X], (body[Y] - other[Y]) / HEIGHT))
            if other[SIZE] >= agent[SIZE]:
                value -= 100.0 if touching else max(0.0, 0.5 - distance) * 4.0
            elif touching:
                value += 10.0
        prey = [o for o in later[step] if o[SIZE] < agent[SIZE] and abs(o[X]) < 1.0]
        if prey:
            value -= min(float(np.hypot(body[X] - o[X], body[Y] - o[Y])) for o in prey)
        return value

    def moved(position: np.ndarray, move: int) -> np.ndarray:
        return np.clip(position + MOVES9[move] * AGENT_STEP, -1.0, 1.0)

    start = agent[[X, Y]]
    totals = []
    for first in range(num_moves):
        position = moved(start, first)
        now = score(position, 0)
        totals.append(now + (0.0 if now <= -100.0 else
                             0.9 * max(score(moved(position, second), 1) for second in range(num_moves))))
    return int(np.argmax(totals))


def record_demonstrations(env: SpritesEnv, transitions: int, seed: int, epsilon: float = 0.0) -> dict[str, np.ndarray]:
    """At least ``transitions`` steps of the scripted expert (:func:`expert_action`), a uniformly random
    move instead with probability ``epsilon``: :func:`envs.demonstrations.record_demonstrations`'s
    arrays (frames, labels, current, actions, episode, returns)."""
    return demonstrations.record_demonstrations(
        env, transitions, seed, epsilon, expert=lambda e: expert_action(e._state, e.num_moves),
        scene=lambda e: e.render_state(e._state))
