"""Chapter 4's tool-use environment (section 4.3, Fig. 4.7 left, bottom) on the robosuite scene of chapter 3.

The UR5e arm and parallel gripper of :class:`envs.manipulation.ManipulationEnv` at a table with an
L-shaped tool, a cube ``block`` that starts out of the arm's reach, and an open box fixed on the
table (layout :data:`envs.manipulation_layout.TOOL_USE`: 15 one-dimensional factors ``eef.x/y/z``,
``grp.0/1``, ``tool.x/y/z/yaw``, ``block.x/y/z``, ``box.x/y/z``), then chapter 4's distractors as in
:class:`envs.block.BlockEnv` (``cd.k``, random projections of the 4-D action; ``ud.k``, U(-1, 1)).

The chapter names the task, "Series: the agent needs to use an L-shaped tool to move a faraway block
within reach, pick it up, and place it within the box", and gives no reward or geometry (the
authors' tool-use scene is not in their released code). Ours, built from the text:

* **Geometry.** The end-effector's goal is clipped to ``x <= 0.2`` (the workspace of chapter 3's
  scene); the block starts at ``x`` in [:data:`BLOCK_FAR_X`, 0.32], where no finger reaches it. The
  tool (handle 26 cm, hook 11 cm across its far end) starts beside the arm with a small random yaw;
  held at its grip point (:data:`envs.manipulation_layout.TOOL_GRIP`), its hook reaches past the
  block. The box (inner 10 x 10 cm, walls 6 cm high) is fixed on the arm's other side.
* **Stages** (``stage_names``; ``info["num_stages"]`` counts those reached so far this episode, in
  order, chapter 5's normalised stage count): ``grasp-tool`` (the closed fingers at the tool's grip
  point with the tool off the table or moving with them), ``pull-block`` (the block pulled within
  reach, ``x <= IN_REACH_X``), ``lift-block`` (the block's centre :data:`LIFT` above its rest),
  ``place-block`` (the block inside the box's walls, released: success, which ends the episode).
* **Reward** in [0, 1], from the state the step reached, the stages' progress:
  ``(reach_tool + pulled + lifted + placed) / 4``, with ``reach_tool = 1 - tanh(10 |eef - grip|)``
  (1 once the block is pulled), ``pulled`` the fraction of the way from :data:`BLOCK_FAR_X` to
  :data:`IN_REACH_X` (in [0, 1]), ``lifted`` the fraction of :data:`LIFT` (1 once in the box) and
  ``placed`` 1 inside the box. 1 on success.

Under the contact-union truth of :mod:`envs.manipulation_truth` every scene factor is an ancestor of
``eef`` and ``block``, so the true minimal abstraction of Series keeps the 15 scene factors and drops
the 40 distractors. ``tool.yaw`` takes part in every contact of the tool (full blocks).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from envs.block import OPEN_FINGER, BlockEnv
from envs.manipulation import yaw_quat
from envs.manipulation_layout import (
    BOX_HEIGHT, BOX_INNER_HALF, BOX_WALL, EEF, MOV_HALF, TABLE_TOP, TOOL_GRIP, TOOL_HANDLE_HALF, TOOL_HOOK_CENTRE,
    TOOL_HOOK_HALF, TOOL_USE,
)
from envs.skills import GRIPPER_STEPS, HOVER, Phase, Skill, grasp
from envs.task_truth import parents_through_step

TASKS = ("series",)
STAGES = ("grasp-tool", "pull-block", "lift-block", "place-block")
BLOCK_FAR_X, IN_REACH_X = 0.27, 0.15
"""The block starts at ``x >= BLOCK_FAR_X`` (out of the fingers' reach); ``pull-block`` is reached at
``x <= IN_REACH_X``."""
LIFT = 0.05
"""Metres the block's centre must rise above its rest for ``lift-block``."""
TOOL_START = ((-0.02, 0.10), (0.02, 0.16))
"""Range (low, high) of the tool's start (x, y); its yaw starts in +-:data:`TOOL_START_YAW`."""
TOOL_START_YAW = 0.15
BLOCK_START = ((BLOCK_FAR_X, -0.06), (0.32, 0.06))
BOX_START = ((-0.15, -0.22), (-0.05, -0.14))
TOOL_LIFT, PULL = 0.07, 0.25
"""Metres the scripted :func:`use_tool` lifts the tool to pass over the block, and pulls it back."""
GRIP_TOLERANCE = 0.03
"""How close (m) the end-effector must be to the tool's grip point for ``grasp-tool``."""
_REST = {"tool": TABLE_TOP[2] + TOOL_HANDLE_HALF[2], "block": TABLE_TOP[2] + MOV_HALF, "box": TABLE_TOP[2] + BOX_WALL}
_S = {o: TOOL_USE.factor_slice(o) for o in ("eef", "grp", "tool", "block", "box")}


class ToolUseEnv(BlockEnv):
    """Observation ``[15 + C + U]`` (the scene's factors, then ``cd.0 ..`` and ``ud.0 ..``); action,
    options and distractors as :class:`envs.block.BlockEnv`; ``task`` is ``"series"``."""

    LAYOUT = TOOL_USE
    ENV_ID = "tool-use"
    TASKS = TASKS

    def __init__(self, *, task: str = "series", **kwargs: Any) -> None:
        super().__init__(task=task, **kwargs)
        self._stages = 0

    @property
    def stage_names(self) -> tuple[str, ...]:
        return STAGES

    @property
    def reward_parents(self) -> np.ndarray:
        """uint8 ``[d + 1]``: the parents at t (action last) of the Series reward, which reads ``eef``,
        ``grp``, ``tool``, ``block`` and ``box`` at t+1."""
        return series_reward_parents(self._global_graph)

    def task_reward(self, scene_obs: np.ndarray) -> tuple[float, bool]:
        reward, stages = series_reward(scene_obs)
        self._stages = max(self._stages, stages)
        return reward, stages == len(STAGES)

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """The scene's reset, then the tool beside the arm, the block out of reach, the box on the
        other side (ranges :data:`TOOL_START`, :data:`BLOCK_START`, :data:`BOX_START`)."""
        super().reset(seed=seed, options=options)
        rng, scene = self.np_random, self.scene
        tool, block, box = (rng.uniform(*r) for r in (TOOL_START, BLOCK_START, BOX_START))
        scene.set_mov_pose(np.r_[tool, _REST["tool"]], yaw_quat(rng.uniform(-TOOL_START_YAW, TOOL_START_YAW)), 0)
        scene.set_mov_pose(np.r_[block, _REST["block"]], yaw_quat(0.0), 1)
        scene.set_kinematic_pose(np.array([[*box, _REST["box"]]]), yaw_quat(0.0)[None])
        scene.commit_poses()
        self._stages = 0
        return self._with_distractors(self._observation()), {"stages": (), "num_stages": 0}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = super().step(action)
        info["num_stages"] = self._stages
        info["stages"] = STAGES[:self._stages]
        return obs, reward, terminated, truncated, info


def _on_tool(obs: np.ndarray, local_xy: tuple[float, float]) -> np.ndarray:
    """World xyz of the point ``local_xy`` of the tool's frame (at the tool's height) in ``obs``."""
    x, y, z, yaw = np.asarray(obs[_S["tool"]], dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    lx, ly = local_xy
    return np.array([x + c * lx - s * ly, y + s * lx + c * ly, z])


def grip_point(scene_obs: np.ndarray) -> np.ndarray:
    """World xyz of the tool's grip point (:data:`envs.manipulation_layout.TOOL_GRIP`) in ``scene_obs``."""
    return _on_tool(scene_obs, TOOL_GRIP)


def series_stages(scene_obs: np.ndarray) -> tuple[dict[str, float], int]:
    """The progress terms of the Series reward and how many stages the state ``scene_obs`` shows,
    each stage counting only once the ones before it are shown too."""
    obs = np.asarray(scene_obs, dtype=np.float64)
    eef, grp, tool, block, box = (obs[_S[o]] for o in ("eef", "grp", "tool", "block", "box"))
    closed = grp[0] < OPEN_FINGER and -grp[1] < OPEN_FINGER
    to_grip = float(np.linalg.norm(eef - grip_point(obs)))
    near_grip = to_grip <= GRIP_TOLERANCE
    holding = bool(closed and near_grip and grp[0] > 0.005)  # fingers stopped by the handle, not shut
    pulled = float(np.clip((BLOCK_FAR_X - block[0]) / (BLOCK_FAR_X - IN_REACH_X), 0.0, 1.0))
    lifted = float(np.clip((block[2] - _REST["block"]) / LIFT, 0.0, 1.0))
    inside = bool(np.all(np.abs(block[:2] - box[:2]) <= BOX_INNER_HALF - MOV_HALF + 0.005)
                  and block[2] <= box[2] + 2 * BOX_HEIGHT)
    released = bool(grp[0] > OPEN_FINGER and -grp[1] > OPEN_FINGER)
    placed = inside and released
    reach_tool = 1.0 if pulled >= 1.0 else float(1.0 - np.tanh(10.0 * to_grip))
    shown = (holding or pulled >= 1.0, pulled >= 1.0, lifted >= 1.0 or inside, placed)
    stages = next((k for k, ok in enumerate(shown) if not ok), len(shown))
    terms = {"reach_tool": reach_tool, "pulled": pulled, "lifted": 1.0 if inside else lifted, "placed": float(placed)}
    return terms, stages


def series_reward(scene_obs: np.ndarray) -> tuple[float, int]:
    """Reward of Series in ``scene_obs`` (the scene's factors first) and the stages it shows."""
    terms, stages = series_stages(scene_obs)
    if stages == len(STAGES):
        return 1.0, stages
    return float(sum(terms.values()) / 4.0), stages


def series_reward_parents(graph: np.ndarray) -> np.ndarray:
    """uint8 ``[d + 1]``: the parents at t of the Series reward given the true one-step ``graph``."""
    read = [i for o in ("eef", "grp", "tool", "block", "box") for i in range(TOOL_USE.num_factors)[_S[o]]]
    return parents_through_step(graph, read)


def _hook(obs: np.ndarray) -> np.ndarray:
    """World xy of the tool's hook centre in ``obs``."""
    return _on_tool(obs, TOOL_HOOK_CENTRE)[:2]


def use_tool(*, max_displacement: float = 0.03) -> Skill:
    """Pull the block within reach with the tool: grasp the handle at its grip point, lift it over
    the block, lower the hook behind the block, pull it towards the arm, let go and rise."""
    def grip(obs: np.ndarray, start: np.ndarray) -> np.ndarray:
        return grip_point(obs) - [0.0, 0.0, 0.004]

    def behind_block(obs: np.ndarray, start: np.ndarray) -> np.ndarray:
        block = obs[_S["block"]]
        goal = np.r_[block[0] + MOV_HALF + TOOL_HOOK_HALF[0] + 0.015, block[1]]
        return np.r_[obs[EEF][:2] + goal - _hook(obs), start[EEF][2]]

    phases = [
        Phase("above-tool", lambda obs, start: grip(obs, start) + [0.0, 0.0, HOVER], 1.0, 25, 0.015),
        Phase("descend", grip, 1.0, 15, 0.008),
        Phase("close", lambda obs, start: start[EEF], 0.0, GRIPPER_STEPS + 2, None),
        Phase("lift", lambda obs, start: start[EEF] + [0.0, 0.0, TOOL_LIFT], 0.0, 10, 0.01),
        Phase("over-block", behind_block, 0.0, 25, 0.01),
        Phase("lower", lambda obs, start: start[EEF] - [0.0, 0.0, TOOL_LIFT - 0.002], 0.0, 10, 0.008),
        Phase("pull", lambda obs, start: start[EEF] - [PULL, 0.0, 0.0], 0.0, 25, 0.01),
        Phase("release", lambda obs, start: start[EEF], 1.0, GRIPPER_STEPS + 1, None),
        Phase("rise", lambda obs, start: start[EEF] + [0.0, 0.0, HOVER], 1.0, 8, 0.015),
    ]
    return Skill("use-tool", phases, max_displacement)


def place_in_box(*, max_displacement: float = 0.03) -> Skill:
    """Carry the held block over the box, lower it inside, open the gripper, rise."""
    def over_box(obs: np.ndarray, start: np.ndarray) -> np.ndarray:
        return np.r_[obs[_S["box"]][:2], obs[_S["box"]][2] + 2 * BOX_HEIGHT + 0.06]

    phases = [
        Phase("over-box", over_box, 0.0, 30, 0.015),
        Phase("lower", lambda obs, start: start[EEF] - [0.0, 0.0, 0.04], 0.0, 8, 0.01),
        Phase("release", lambda obs, start: start[EEF], 1.0, GRIPPER_STEPS + 1, None),
        Phase("rise", lambda obs, start: start[EEF] + [0.0, 0.0, HOVER], 1.0, 8, 0.015),
    ]
    return Skill("place-in-box", phases, max_displacement)


class SeriesScript:
    """The scripted Series solution: :func:`use_tool`, then grasp the block, then :func:`place_in_box`.
    :meth:`act` gives the next action, None once the script is done."""

    def __init__(self, *, max_displacement: float = 0.03) -> None:
        self.skills = [use_tool(max_displacement=max_displacement),
                       grasp("block", max_displacement=max_displacement, layout=TOOL_USE),
                       place_in_box(max_displacement=max_displacement)]

    def act(self, obs: np.ndarray) -> np.ndarray | None:
        while self.skills:
            action = self.skills[0].act(obs)
            if action is not None:
                return action
            self.skills.pop(0)
        return None
