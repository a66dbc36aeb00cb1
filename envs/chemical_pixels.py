"""Chemical rendered to pixels with exact per-object masks (the rendered env of chapter 7 / issue 24).

Chemical's dynamics unchanged (colours propagate along the object DAG; positions depend on nothing),
drawn as small RGB frames: object ``k`` is a fixed shape (square, circle, diamond, triangle, plus:
``k mod 5``) filled with its colour's palette entry, centred at its ``(x, y)`` position, on a black
background. Positions are frame coordinates in ``(-1, 1)`` (``-1``: left or top edge), re-drawn
i.i.d. every step as in Chemical, but spread over the frame: each object gets its own cell of a
``ceil(sqrt(N))``-square grid (a uniformly random assignment) and a uniform offset inside it, so
shapes never overlap and every object is always visible. The renderer therefore knows each pixel's
object exactly: ``info["masks"]`` stands in for the segmentation model (SAM2) of chapter 7.

The observation stays Chemical's factored state (every service runs this env unchanged, and a
state-based run is its own baseline); the frame is in ``info["frame"]`` and ``render()``.
"""
from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np

from envs.chemical import ChemicalEnv
from proto.messages import EnvSpec

PALETTE = np.array([
    (230, 25, 75), (60, 180, 75), (0, 130, 200), (255, 225, 25), (240, 50, 230),
    (70, 240, 240), (245, 130, 48), (145, 30, 180), (210, 245, 60), (250, 190, 212),
], dtype=np.uint8)
"""RGB of colour index ``c`` (distinct on a black background); ``num_colors`` is at most its length."""

SHAPES = ("square", "circle", "diamond", "triangle", "plus")
"""Object ``k`` is drawn as ``SHAPES[k % len(SHAPES)]``."""

FILL = 0.75
"""A shape's width as a fraction of its grid cell; the rest is the room its position moves in."""

PART_COLOR = np.array((200, 200, 200), dtype=np.uint8)
"""With ``two_tone``, the colour of every shape's lower half (light grey: not in :data:`PALETTE`)."""


class ChemicalPixelsEnv(ChemicalEnv):
    """Chemical whose states are also drawn as ``frame_size`` x ``frame_size`` RGB frames.

    Observation, action, reward, ground truth: Chemical's (``position_std`` and ``ood_noise_scale``
    do not apply: positions are the frame layout described in the module docstring). Every step's
    and reset's ``info`` adds ``frame`` (uint8 ``[H, W, 3]``) and ``masks`` (bool ``[N + 1, H, W]``:
    channel 0 the background, channel ``1 + k`` object ``k``; the channels partition the frame).
    ``render_mode="rgb_array"`` makes :meth:`render` return the frame.
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, *, frame_size: int = 32, two_tone: bool = False, render_mode: str | None = None,
                 **kwargs: Any) -> None:
        if kwargs.get("ood_noise_scale") is not None:
            raise ValueError("chemical-pixels draws positions from its frame layout: ood_noise_scale does not apply")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        super().__init__(**kwargs)
        self.render_mode = render_mode
        self.frame_size = frame_size
        self.two_tone = bool(two_tone)
        """Each shape's lower half drawn in :data:`PART_COLOR`, its upper half in its colour: objects of two
        parts, where the parts of different objects look more alike than the two parts of one object (the
        scene in which unsupervised slots split objects, chapter 7's case for the mask prior)."""
        self.grid = math.ceil(math.sqrt(self.num_objects))
        if self.num_colors > len(PALETTE):
            raise ValueError(f"chemical-pixels draws at most {len(PALETTE)} colours, got num_colors={self.num_colors}")
        if frame_size < 4 * self.grid:
            raise ValueError(f"frame_size {frame_size} leaves under 4 pixels per object cell ({self.grid} per side)")
        self.shape_ids = np.arange(self.num_objects) % len(SHAPES)

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Chemical's reset; ``info`` carries the frame and the masks."""
        obs, info = super().reset(seed=seed, options=options)
        return obs, {**info, **self._frame_info(obs)}

    def step(self, action: int | np.integer) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Chemical's step; ``info`` also carries the frame and the masks."""
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, reward, terminated, truncated, {**info, **self._frame_info(obs)}

    def render(self) -> np.ndarray | None:  # type: ignore[override]
        """``rgb_array``: the current frame (uint8 ``[H, W, 3]``)."""
        if self.render_mode != "rgb_array":
            return None
        return self.render_states(self._observation()[None])[0][0]

    def sample_states(self, count: int) -> np.ndarray:
        """``count`` states (float ``[count, 3N]``) drawn as :meth:`reset` draws one (uniform colours, a
        fresh layout), from this env's generator: a seeded source of frames for representation learning."""
        colors = self.np_random.integers(0, self.num_colors, size=(count, self.num_objects))
        return self._pack(colors, self._draw_positions((count, self.num_objects, 2)))

    def render_states(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames and instance labels of a batch of states (float ``[B, 3N]``), vectorised over the batch.

        Returns ``frames`` uint8 ``[B, H, W, 3]`` and ``labels`` uint8 ``[B, H, W]`` (0: background,
        ``1 + k``: object ``k``; where shapes would overlap the later object is on top)."""
        colors = self._colors_of(np.asarray(states, dtype=np.float64))
        positions = np.asarray(states, dtype=np.float64).reshape(len(colors), self.num_objects, 3)[..., 1:]
        inside = self._inside(positions)
        labels = np.zeros(inside.shape[:1] + inside.shape[2:], dtype=np.uint8)
        for k in range(self.num_objects):
            labels[inside[:, k]] = k + 1
        rgb = np.concatenate([np.zeros((len(colors), 1, 3), np.uint8), PALETTE[colors]], axis=1)
        frames = rgb[np.arange(len(colors))[:, None, None], labels]
        if self.two_tone:
            lower = self._pixel_offsets(positions)[1] > 0
            for k in range(self.num_objects):
                frames[(labels == k + 1) & lower[:, k]] = PART_COLOR
        return frames, labels

    def env_spec(self) -> EnvSpec:
        """Chemical's spec, named ``chemical-pixels``, positions scaled to their spread over the frame."""
        spec = super().env_spec()
        scales = (1.0, 1.0 / math.sqrt(3.0), 1.0 / math.sqrt(3.0)) * self.num_objects
        return dataclasses.replace(spec, env_id="chemical-pixels", factor_scales=scales,
                                   config_json=json.dumps(self.config()))

    def config(self) -> dict[str, Any]:
        """Chemical's configuration plus ``frame_size`` and ``two_tone``."""
        return {**super().config(), "frame_size": self.frame_size, "two_tone": self.two_tone}

    def _frame_info(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        frames, labels = self.render_states(obs[None])
        return {"frame": frames[0], "masks": masks_from_labels(labels[0], self.num_objects)}

    def _draw_positions(self, shape: tuple[int, ...]) -> np.ndarray:
        """Positions ``shape`` = ``(..., N, 2)``: a random grid cell per object, a uniform offset in it."""
        batch, n, g = shape[:-2], shape[-2], self.grid
        cells = np.argsort(self.np_random.random(batch + (g * g,)), axis=-1)[..., :n]
        cell_centres = np.stack([cells % g, cells // g], axis=-1) + 0.5
        slack = (1.0 - FILL) / 2.0
        offsets = self.np_random.uniform(-slack, slack, size=shape)
        return (cell_centres + offsets) * (2.0 / g) - 1.0

    def _pixel_offsets(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``dx`` ``[B, N, 1, W]`` and ``dy`` ``[B, N, H, 1]``: each pixel centre's offset from each object's
        centre, in pixels (``dy > 0``: below it)."""
        pixel = np.arange(self.frame_size) + 0.5
        centres = (positions + 1.0) * (self.frame_size / 2.0)
        return (pixel[None, None, None, :] - centres[..., 0, None, None],
                pixel[None, None, :, None] - centres[..., 1, None, None])

    def _inside(self, positions: np.ndarray) -> np.ndarray:
        """bool ``[B, N, H, W]``: which pixels each object's shape covers."""
        dx, dy = self._pixel_offsets(positions)
        r = FILL * self.frame_size / (2.0 * self.grid)
        ax, ay = np.abs(dx), np.abs(dy)
        arm = r / 2.5
        drawn = np.stack([
            np.maximum(ax, ay) <= r * 0.85,
            dx * dx + dy * dy <= r * r,
            ax + ay <= r * 1.1,
            (ay <= r) & (ax <= (dy + r) / 2.0),
            ((ax <= arm) & (ay <= r)) | ((ay <= arm) & (ax <= r)),
        ])
        return drawn[self.shape_ids, :, np.arange(self.num_objects)].transpose(1, 0, 2, 3)


def masks_from_labels(labels: np.ndarray, num_objects: int) -> np.ndarray:
    """bool ``[..., N + 1, H, W]`` one-hot instance masks of labels ``[..., H, W]`` (channel 0: background)."""
    return np.asarray(labels)[..., None, :, :] == np.arange(num_objects + 1)[:, None, None]
