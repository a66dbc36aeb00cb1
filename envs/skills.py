"""Scripted skill primitives for the manipulation environment and the chapter's "Uniform" collection
policy over them (dissertation 3.3.1, following the parameterised primitives of Nasiriany et al.).

A skill is a fixed sequence of phases; each phase drives the end-effector towards a target that it
computes from the current observation (and the observation the phase started from) with a fixed
gripper opening, and ends when the end-effector is within the phase's tolerance of its target or its
step budget is spent. Skills read only the observation (layout :mod:`envs.manipulation_layout`) and
emit the environment's 4-D actions ``[dx, dy, dz, opening]``, so they need no simulator.

* :func:`reach` ``(target, opening)``: move the end-effector to ``target``.
* :func:`grasp` ``(obj)``: hover above the cube, descend open, close, lift.
* :func:`push` ``(obj, direction, distance)``: lower the closed gripper behind the cube and push it
  ``distance`` metres along the horizontal angle ``direction``, then lift away.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import gymnasium as gym
import numpy as np

from envs.manipulation_layout import (
    EEF, FIXED_HALF, MANIPULATION, MOV_HALF, TABLE_TOP, WORKSPACE_HIGH, WORKSPACE_LOW, SceneLayout,
)

SKILLS = ("reach", "grasp", "push")
CUBES = ("mov", "unm", "rand")
OPTIONS: tuple[tuple[str, str | None], ...] = (("reach", None),) + tuple(
    (skill, obj) for skill in ("grasp", "push") for obj in CUBES)
"""The skill action space of a policy that acts over skills (the chapter's PPO over skills): a
skill and its object; the continuous parameters (reach target and opening, push direction and
distance) stay uniformly random, drawn when the option is taken."""
OPTION_NAMES = tuple(skill if obj is None else f"{skill}:{obj}" for skill, obj in OPTIONS)
HOVER = 0.08
"""Height above a cube's centre from which grasps and pushes start (m)."""
LIFT = 0.12
GRIPPER_STEPS = 3
"""Steps the gripper is given to open or close fully."""
PUSH_STANDOFF = 0.05
"""Distance behind a cube's centre where a push starts (half a cube, half a finger, a margin)."""

RESET_JUMP = 0.1
"""End-effector displacement between two observations (m) that only a reset can cause."""

Target = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``(observation, observation at the start of the phase) -> end-effector target (world xyz)``."""


@dataclass(frozen=True)
class Phase:
    name: str
    target: Target
    opening: float
    """Gripper opening in [0, 1] (0 closed) held throughout the phase."""
    max_steps: int
    tolerance: float | None = 0.01
    """End the phase once the end-effector is this close (m) to its target; None: run all steps."""
    min_steps: int = 0
    """Steps the phase runs even at its target (to let the gripper reach its opening)."""


class Skill:
    """A running skill: :meth:`act` gives the next action, or None once every phase has ended."""

    def __init__(self, name: str, phases: list[Phase], max_displacement: float = 0.03) -> None:
        self.name, self.phases, self.max_displacement = name, phases, max_displacement
        self.phase_index, self.phase_steps = 0, 0
        self._phase_start: np.ndarray | None = None

    @property
    def done(self) -> bool:
        return self.phase_index >= len(self.phases)

    @property
    def phase(self) -> str | None:
        return None if self.done else self.phases[self.phase_index].name

    def act(self, observation: np.ndarray) -> np.ndarray | None:
        obs = np.asarray(observation, dtype=np.float64)
        while not self.done:
            phase = self.phases[self.phase_index]
            if self._phase_start is None:
                self._phase_start = obs.copy()
            error = phase.target(obs, self._phase_start) - obs[EEF]
            reached = (phase.tolerance is not None and np.linalg.norm(error) < phase.tolerance
                       and self.phase_steps >= phase.min_steps)
            if reached or self.phase_steps >= phase.max_steps:
                self.phase_index, self.phase_steps, self._phase_start = self.phase_index + 1, 0, None
                continue
            self.phase_steps += 1
            move = np.clip(error / self.max_displacement, -1.0, 1.0)
            return np.r_[move, phase.opening].astype(np.float32)
        return None


def _cube(obs: np.ndarray, obj: str, layout: SceneLayout = MANIPULATION) -> np.ndarray:
    return obs[layout.factor_slice(obj)][:3]


def _half(obj: str) -> float:
    return MOV_HALF if obj == "mov" else FIXED_HALF


def reach(target: np.ndarray, opening: float = 1.0, *, max_steps: int = 25, max_displacement: float = 0.03) -> Skill:
    """Move the end-effector to ``target`` (world xyz, clipped to the workspace) with the gripper
    held at ``opening``."""
    goal = np.clip(np.asarray(target, dtype=np.float64), WORKSPACE_LOW, WORKSPACE_HIGH)
    phase = Phase("reach", lambda obs, start: goal, opening, max_steps, min_steps=GRIPPER_STEPS)
    return Skill("reach", [phase], max_displacement)


def grasp(obj: str = "mov", *, max_displacement: float = 0.03, layout: SceneLayout = MANIPULATION) -> Skill:
    """Pick ``obj`` (a cube of ``layout``) up: hover above it, descend with the gripper open, close,
    lift ``LIFT`` metres."""
    def above(obs: np.ndarray, start: np.ndarray) -> np.ndarray:
        return _cube(obs, obj, layout) + [0.0, 0.0, HOVER]

    def around(obs: np.ndarray, start: np.ndarray) -> np.ndarray:
        return _cube(obs, obj, layout) - [0.0, 0.0, 0.005]

    def hold(obs: np.ndarray, start: np.ndarray) -> np.ndarray:
        return start[EEF]

    def lifted(obs: np.ndarray, start: np.ndarray) -> np.ndarray:
        return start[EEF] + [0.0, 0.0, LIFT]

    phases = [
        Phase("above", above, 1.0, 25, 0.015),
        Phase("descend", around, 1.0, 15, 0.008),
        Phase("close", hold, 0.0, GRIPPER_STEPS + 2, None),  # and squeeze
        Phase("lift", lifted, 0.0, 15, 0.015),
    ]
    return Skill("grasp", phases, max_displacement)


def push(obj: str = "mov", direction: float = 0.0, distance: float = 0.1, *, max_displacement: float = 0.03) -> Skill:
    """Push ``obj`` by ``distance`` metres along the horizontal angle ``direction`` (radians from
    +x): hover behind it, lower the closed gripper to its centre height, push, lift away."""
    u = np.array([np.cos(direction), np.sin(direction), 0.0])
    height = TABLE_TOP[2] + _half(obj)

    def behind(obs: np.ndarray) -> np.ndarray:
        return np.r_[_cube(obs, obj)[:2], height] - PUSH_STANDOFF * u

    phases = [
        Phase("hover", lambda obs, start: behind(start) + [0.0, 0.0, HOVER], 0.0, 25, 0.015),
        Phase("lower", lambda obs, start: behind(start), 0.0, 10, 0.01),
        Phase("push", lambda obs, start: start[EEF] + (PUSH_STANDOFF + distance) * u, 0.0, 15, 0.01),
        Phase("retreat", lambda obs, start: start[EEF] + [0.0, 0.0, HOVER], 0.0, 8, 0.015),
    ]
    return Skill("push", phases, max_displacement)


class SkillPolicy:
    """Runs skills to completion, one after another: usable by an env-worker as ``act(obs) -> action``.

    Which skill comes next is an *option* (an index into :data:`OPTIONS`), chosen by ``chooser(obs)``
    when one is given (a policy over skills, the chapter's PPO) and otherwise by the chapter's
    "Uniform" policy: a uniformly random skill of ``skills``, grasps of a uniform cube of
    ``grasp_objects``, pushes of a uniform cube of ``push_objects``. :attr:`last_option` is the option
    chosen by the last :meth:`act` (-1 while a skill runs on), so the steps where a decision was made
    can be marked in the data. Parameters are uniform: reach targets over the workspace with a
    uniform gripper opening, pushes in a uniform direction by U(0.02, 0.15) m. Skills take the object
    as a parameter and do not know which cube can move (as the chapter's skill-space PPO does not): a
    grasp of ``unm`` or ``rand`` closes on a cube that holds the fingers back, and the lift that
    follows is where the arm's motion depends on those cubes for many steps in a row, the
    action-relevant edges of 3.3.1. ``action_noise`` is the standard deviation of Gaussian noise
    added to the displacement part of every action (diversity for dynamics learning), clipped to
    the space.

    The env-worker calls :meth:`reset` at episode ends; as a fallback for callers that do not, an
    end-effector that jumps farther than any step can move it (the arm was reset) also drops the
    running skill.
    """

    version = 0
    over_skills = True
    OPTION_NAMES = OPTION_NAMES
    """The options a policy over these skills picks among (the env registry reads them from here)."""

    def __init__(
        self,
        action_space: gym.spaces.Box,
        seed: int,
        *,
        max_displacement: float = 0.03,
        action_noise: float = 0.1,
        skills: tuple[str, ...] = SKILLS,
        push_objects: tuple[str, ...] = CUBES,
        grasp_objects: tuple[str, ...] = CUBES,
        chooser: Callable[[np.ndarray], int] | None = None,
    ) -> None:
        unknown = set(skills) - set(SKILLS) or (set(push_objects) | set(grasp_objects)) - set(CUBES)
        if unknown:
            raise ValueError(f"unknown skills or objects {sorted(unknown)}; known: {SKILLS}, {CUBES}")
        self.low, self.high = action_space.low, action_space.high
        self.rng = np.random.default_rng(seed)
        self.max_displacement, self.action_noise = max_displacement, action_noise
        self.skills, self.push_objects, self.grasp_objects = skills, push_objects, grasp_objects
        self.chooser = chooser
        self.skill: Skill | None = None
        self.last_option = -1
        self._last_eef: np.ndarray | None = None

    def reset(self) -> None:
        """Drop the running skill (a new episode starts)."""
        self.skill, self._last_eef = None, None

    def act(self, observation: np.ndarray) -> np.ndarray:
        eef = np.asarray(observation, dtype=np.float64)[EEF]
        if self._last_eef is not None and np.linalg.norm(eef - self._last_eef) > RESET_JUMP:
            self.skill = None
        self._last_eef = eef
        self.last_option = -1
        for _ in range(10):  # a skill whose every phase is already satisfied yields no action
            if self.skill is None:
                self.last_option = self.choose(observation)
                self.skill = self.build(self.last_option)
            action = self.skill.act(observation)
            if action is not None:
                noise = np.r_[self.rng.normal(0.0, self.action_noise, 3), 0.0] if self.action_noise else 0.0
                return np.clip(action + noise, self.low, self.high).astype(np.float32)
            self.skill = None
        return np.r_[0.0, 0.0, 0.0, 1.0].astype(np.float32)

    def choose(self, observation: np.ndarray) -> int:
        """The next option: ``chooser``'s, or the Uniform policy's."""
        if self.chooser is not None:
            option = int(self.chooser(observation))
            if not 0 <= option < len(OPTIONS):
                raise ValueError(f"option {option} out of range: {len(OPTIONS)} options {OPTION_NAMES}")
            return option
        return self.uniform_option()

    def uniform_option(self) -> int:
        """An option of the Uniform policy: a uniform skill, then a uniform object for it."""
        name = self.skills[self.rng.integers(len(self.skills))]
        if name == "reach":
            return OPTIONS.index(("reach", None))
        objects = self.grasp_objects if name == "grasp" else self.push_objects
        return OPTIONS.index((name, objects[self.rng.integers(len(objects))]))

    def sample_skill(self) -> Skill:
        """A skill of the Uniform policy."""
        return self.build(self.uniform_option())

    def build(self, option: int) -> Skill:
        """The skill of ``option`` with uniformly random parameters."""
        name, obj = OPTIONS[option]
        d = self.max_displacement
        if name == "reach":
            target = self.rng.uniform(WORKSPACE_LOW, WORKSPACE_HIGH)
            return reach(target, float(self.rng.uniform(0.0, 1.0)), max_displacement=d)
        if name == "grasp":
            return grasp(obj, max_displacement=d)
        direction, distance = self.rng.uniform(0.0, 2 * np.pi), self.rng.uniform(0.02, 0.15)
        return push(obj, float(direction), float(distance), max_displacement=d)
