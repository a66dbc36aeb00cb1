"""Chapter 4's block environment (section 4.3, Fig. 4.7 left) on the robosuite scene of chapter 3.

The UR5e arm and parallel gripper of :class:`envs.manipulation.ManipulationEnv` at a table with three
movable cubes ``mov1``-``mov3`` and one cube ``unm`` fixed to the table (layout
:data:`envs.manipulation_layout.BLOCK`: 17 one-dimensional factors ``eef.x/y/z``, ``grp.0/1``, ``x/y/z``
of ``mov1``, ``mov2``, ``mov3``, ``unm``), then chapter 4's distractors (:mod:`envs.distractors`):
``cd.k``, random projections of the 4-D action, and ``ud.k``, U(-1, 1) every step (``"20,20"`` as the
chapter). Same action, control rate and episode length as chapter 3's scene.

Tasks (the chapter names them, "Pick" and "Stack", without defining their rewards; these follow
chapter 3's task list, "pick the movable object to the goal position" and "stack the movable object
on the top of the unmovable object", with a fixed height instead of a sampled goal):

* ``pick``: lift ``mov1`` so that its centre is :data:`PICK_HEIGHT` above where it rests on the table.
  Reward ``0.5 reach + 0.5 lift`` with ``reach = 1 - tanh(10 |eef - mov1|)`` and ``lift`` the fraction
  of the height reached (in [0, 1]); 1 on success.
* ``stack``: put ``mov1`` on top of ``unm`` and let go: its centre within :data:`STACK_XY` of ``unm``'s
  axis and :data:`STACK_Z` of resting height on it, both fingers open wider than the cube. Reward
  ``0.5 reach + 0.5 (1 - tanh(10 |mov1 - on_unm|))``; 1 on success.

Success ends the episode (``terminated``) and is ``info["success"]``. Rewards are computed from the
state the step reached; their true parents at t (``reward_parents``) follow through one step of the
true graph (:func:`envs.task_truth.parents_through_step`). Under the contact-union truth of
:mod:`envs.manipulation_truth` any cube can block the arm, so every scene factor is an ancestor of
``eef`` and ``mov1``: the true minimal abstraction of both tasks keeps the 17 scene factors and drops
the 40 distractors (Fig. 4.5's CBM also drops ``mov2`` and ``mov3``: see docs/deviations.md).
"""
from __future__ import annotations

import dataclasses
import json
from typing import Any

import gymnasium as gym
import numpy as np

from envs.distractors import Distractors, parse_distractors
from envs.manipulation import ManipulationEnv
from envs.manipulation_layout import BLOCK, FIXED_HALF, MOV_HALF, TABLE_TOP
from envs.task_truth import parents_through_step
from proto.messages import EnvSpec

TASKS = ("pick", "stack")
PICK_HEIGHT = 0.08
"""Metres ``mov1``'s centre must rise above its resting height for ``pick``."""
STACK_XY, STACK_Z = 0.015, 0.01
"""Tolerances of ``stack`` (metres): horizontal offset from ``unm``'s axis, height off resting on it."""
OPEN_FINGER = 0.022
"""A finger further than this from the centre holds nothing as wide as a cube (half-width 0.02)."""
_EEF, _GRP, _MOV1, _UNM = (BLOCK.factor_slice(o) for o in ("eef", "grp", "mov1", "unm"))
_REST_Z = TABLE_TOP[2] + MOV_HALF
_ON_UNM = np.array([0.0, 0.0, FIXED_HALF + MOV_HALF])


class BlockEnv(ManipulationEnv):
    """Observation ``[17 + C + U]`` (the scene's factors, then ``cd.0 ..`` and ``ud.0 ..``); action and
    every :class:`ManipulationEnv` option as there. ``task`` is one of :data:`TASKS`, ``distractors``
    ``"C,U"``, ``distractor_seed`` fixes the projection, ``distractor_ood = (lo, hi)`` lifts distractor
    values out of their training range (:class:`envs.distractors.Distractors`)."""

    LAYOUT = BLOCK
    ENV_ID = "block"
    TASKS = TASKS

    def __init__(self, *, task: str = "pick", distractors: str = "20,20", distractor_seed: int = 0,
                 distractor_ood: tuple[float, float] | None = None, **kwargs: Any) -> None:
        if task not in self.TASKS:
            raise ValueError(f"task must be one of {self.TASKS}, got {task!r}")
        controllable, uncontrollable = parse_distractors(distractors)
        self.task, self.distractor_seed = task, distractor_seed
        self.distractors = Distractors(controllable, uncontrollable, "continuous", 4, distractor_seed,
                                       None if distractor_ood is None else tuple(distractor_ood))
        super().__init__(**kwargs)
        self._scene_graph = self._global_graph
        self._global_graph = self.distractors.extend_graph(self._scene_graph)
        self._global_graph.flags.writeable = False
        bound = np.r_[self.observation_space.high, np.full(self.distractors.count, self.distractors.bound)]
        self.observation_space = gym.spaces.Box(-bound.astype(np.float32), bound.astype(np.float32), dtype=np.float32)
        self._values = np.zeros(self.distractors.count)

    @property
    def factor_names(self) -> tuple[str, ...]:
        return self.layout.factor_names + self.distractors.names

    @property
    def reward_parents(self) -> np.ndarray:
        """uint8 ``[d + 1]``: the true parents at t (action last) of the task's reward, which reads
        ``eef`` and ``mov1`` (``pick``), and ``grp`` and ``unm`` too (``stack``) at t+1."""
        return task_reward_parents(self.task, self._global_graph)

    def task_reward(self, scene_obs: np.ndarray) -> tuple[float, bool]:
        """Reward and success of the task in the state ``scene_obs`` (the scene's factors)."""
        return task_reward(self.task, scene_obs)

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """The scene's reset, controllable distractors at 0, uncontrollable ones drawn."""
        scene_obs, info = super().reset(seed=seed, options=options)
        self._values = self.distractors.reset(self.np_random)
        return self._with_distractors(scene_obs), info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """The scene's step, the distractors' new values, the task's reward and success."""
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(4), self.action_space.low, self.action_space.high)
        scene_obs, _, _, truncated, info = super().step(a)
        self._values = self.distractors.step(a, self.np_random)
        obs = self._with_distractors(scene_obs)
        reward, success = self.task_reward(scene_obs)
        info["local_graph"] = self.distractors.extend_graph(info["local_graph"])
        info["success"] = success
        return obs, reward, success, truncated, info

    def restore(self, snapshot: Any) -> np.ndarray:
        """Return to ``snapshot``; the distractors keep their current values (they read no state)."""
        return self._with_distractors(super().restore(snapshot))

    def intervene(self, values: dict[str, float]) -> np.ndarray:
        """Set scene factors (as :meth:`ManipulationEnv.intervene`) and distractors by name."""
        scene = {k: v for k, v in values.items() if k not in self.distractors.names}
        for name in set(values) - set(scene):
            self._values[self.distractors.names.index(name)] = values[name]
        return self._with_distractors(super().intervene(scene))

    def env_spec(self) -> EnvSpec:
        """The scene's spec with the distractors (continuous, scale 1) and the true reward parents."""
        spec, m = super().env_spec(), self.distractors.count
        return dataclasses.replace(
            spec, factor_names=self.factor_names, factor_kinds=spec.factor_kinds + ("continuous",) * m,
            factor_sizes=spec.factor_sizes + (1,) * m, factor_objects=spec.factor_objects + self.distractors.objects,
            factor_locs=spec.factor_locs + (0.0,) * m, factor_scales=spec.factor_scales + (1.0,) * m,
            global_graph=self._global_graph.copy(), reward_parents=self.reward_parents,
            config_json=json.dumps(self.config()),
        )

    def config(self) -> dict[str, Any]:
        d = self.distractors
        return {**super().config(), "task": self.task, "distractors": f"{d.controllable},{d.uncontrollable}",
                "distractor_seed": self.distractor_seed,
                **({"distractor_ood": list(d.ood_range)} if d.ood_range else {})}

    def _with_distractors(self, scene_obs: np.ndarray) -> np.ndarray:
        return np.concatenate([scene_obs, self._values.astype(np.float32)])


def task_reward_parents(task: str, graph: np.ndarray) -> np.ndarray:
    """uint8 ``[d + 1]``: the parents at t of ``task``'s reward given the true one-step ``graph``
    (the block scene's factors first)."""
    objects = ("eef", "mov1") if task == "pick" else ("eef", "grp", "mov1", "unm")
    read = [i for o in objects for i in range(BLOCK.num_factors)[BLOCK.factor_slice(o)]]
    return parents_through_step(graph, read)


def task_reward(task: str, obs: np.ndarray) -> tuple[float, bool]:
    """Reward and success of ``task`` in the state ``obs`` (the scene's factors first)."""
    eef, grp, mov1, unm = (np.asarray(obs[s], dtype=np.float64) for s in (_EEF, _GRP, _MOV1, _UNM))
    reach = 1.0 - np.tanh(10.0 * np.linalg.norm(eef - mov1))
    if task == "pick":
        lift = np.clip((mov1[2] - _REST_Z) / PICK_HEIGHT, 0.0, 1.0)
        success = bool(lift >= 1.0)
        return (1.0 if success else float(0.5 * reach + 0.5 * lift)), success
    offset = mov1 - (unm + _ON_UNM)
    released = bool(grp[0] > OPEN_FINGER and -grp[1] > OPEN_FINGER)
    success = bool(np.linalg.norm(offset[:2]) <= STACK_XY and abs(offset[2]) <= STACK_Z and released)
    return (1.0 if success else float(0.5 * reach + 0.5 * (1.0 - np.tanh(10.0 * np.linalg.norm(offset))))), success
