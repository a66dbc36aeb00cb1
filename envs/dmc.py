"""DeepMind Control Suite tasks with chapter 4's distractors (section 4.3: Cheetah and Walker, Fig. 4.7).

"In the DMC, we consider the Cheetah and Walker tasks, two high-dimensional continuous control tasks.
In all environments, as controllable distractors (cd), 20 factors whose values are random projections
of the action [...] 20 uncontrollable distractors [...]" The suite's own state observation is the
scene's factors, one dimension each, named after the model's bodies and joints:

* ``walker`` (task ``walk``, also ``stand``, ``run``): ``<body>.xx`` and ``<body>.xz`` of the 7 bodies'
  orientations (torso, thighs, legs, feet), ``height`` (the torso's), and ``<joint>.vel`` of the 9
  joints (rootz, rootx, rooty, hips, knees, ankles): 24 factors;
* ``cheetah`` (task ``run``): ``<joint>.pos`` of the 8 joints but ``rootx`` and ``<joint>.vel`` of all 9:
  17 factors;

then ``cd.k`` (``P_k . a``, the 6-D action) and ``ud.k`` (U(-1, 1)), :mod:`envs.distractors`. Action:
the suite's 6 torques in [-1, 1]; reward the suite's (in [0, 1] per step); episodes never terminate
and truncate after ``episode_length`` steps (the suite's 1,000 by default).

**Truth.** Neither the chapter nor the suite gives a graph. Ours: the scene's one-step graph is dense,
every factor at t+1 reading every scene factor at t and the action. An articulated body's
accelerations are its inverse mass matrix times the forces, and that matrix couples every joint
coordinate with every other (the orientations and the height are functions of the coordinates);
ground contacts couple them again. A control step spans several physics steps, so each factor reads
the others through that coupling. This is an assumption, not a measurement (``docs/deviations.md``).
The distractors add their rows and columns as everywhere. So the reward's true parents are every
scene factor and the action; the true minimal abstraction keeps the scene and drops the 40 distractors.

``dm_control`` is an optional dependency (``pip install -e '.[dmc]'``, which ``make venv`` does); the
service image does not carry it.
"""
from __future__ import annotations

import json
import os
from typing import Any

import gymnasium as gym
import numpy as np

from envs.distractors import Distractors, parse_distractors
from proto.messages import EnvSpec

DOMAINS = {"walker": ("walk", "stand", "run"), "cheetah": ("run",)}
"""Suite domains and the tasks each poses here (the first is the default)."""
ACTION_SIZE = 6
SCENE_BOUND = 1000.0
"""Observation-space bound on the scene's factors, far outside anything the suite reaches."""
_NORMALISATION = {
    # the random policy's mean and standard deviation per factor (5 episodes of seed 0, one digit)
    "walker": ([-0.08, 0.2, -0.1, 0.3, 0.02, 0.2, 0.08, 0.2, -0.1, 0.3, -0.03, 0.1, 0.03, 0.1, 0.2,
                -0.04, 0.03, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
               [0.3, 0.9, 0.6, 0.7, 0.7, 0.7, 0.7, 0.6, 0.6, 0.7, 0.6, 0.8, 0.7, 0.7, 0.2,
                0.7, 0.5, 3.0, 7.0, 6.0, 10.0, 7.0, 6.0, 10.0]),
    "cheetah": ([-0.1, 0.05, 0.01, 0.04, -0.04, -0.06, -0.1, -0.1, -0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                [0.03, 0.05, 0.1, 0.1, 0.1, 0.07, 0.1, 0.1, 0.4, 0.4, 0.9, 3.0, 4.0, 4.0, 2.0, 3.0, 3.0]),
}


class DMCEnv(gym.Env[np.ndarray, np.ndarray]):
    """A suite task as a factored gymnasium environment with distractors.

    ``domain`` is ``walker`` or ``cheetah`` (:data:`DOMAINS`), ``task`` one of its tasks (its first by
    default), ``distractors`` ``"C,U"``, ``distractor_seed`` fixes the projection and
    ``distractor_ood = (lo, hi)`` lifts the distractors' values out of their training range, as in
    :class:`envs.block.BlockEnv`. ``reset(seed=s)`` fixes the episode (the suite's initial state and the
    distractors' draws)."""

    metadata = {"render_modes": []}
    DOMAIN = "walker"
    ENV_ID = "dmc-walker"

    def __init__(self, *, task: str = "", distractors: str = "20,20", distractor_seed: int = 0,
                 distractor_ood: tuple[float, float] | None = None, episode_length: int = 1000) -> None:
        tasks = DOMAINS[self.DOMAIN]
        task = task or tasks[0]
        if task not in tasks:
            raise ValueError(f"task must be one of {tasks}, got {task!r}")
        if episode_length < 1:
            raise ValueError(f"episode_length must be >= 1, got {episode_length}")
        controllable, uncontrollable = parse_distractors(distractors)
        # the suite's environments are never rendered here: without this dm_control's import opens a
        # GLFW (X11) renderer, which warns on a machine without a display
        os.environ.setdefault("MUJOCO_GL", "disable")
        try:
            from dm_control import suite
        except ImportError as exc:  # an optional dependency: say how to get it
            raise ImportError("the DMC environments need dm_control: pip install -e '.[dmc]' (make venv does)") from exc
        self._suite = suite
        self.task, self.episode_length, self.distractor_seed = task, episode_length, distractor_seed
        self.distractors = Distractors(controllable, uncontrollable, "continuous", ACTION_SIZE, distractor_seed,
                                       None if distractor_ood is None else tuple(distractor_ood))
        self._env = suite.load(self.DOMAIN, task, task_kwargs={"random": 0})
        self.scene_names = _scene_names(self.DOMAIN, self._env.physics)
        n = len(self.scene_names)
        scene_graph = np.ones((n, n + 1), dtype=np.uint8)
        self._global_graph = self.distractors.extend_graph(scene_graph)
        self._global_graph.flags.writeable = False
        bound = np.r_[np.full(n, SCENE_BOUND), np.full(self.distractors.count, self.distractors.bound)]
        self.observation_space = gym.spaces.Box(-bound.astype(np.float32), bound.astype(np.float32), dtype=np.float32)
        self.action_space = gym.spaces.Box(-np.ones(ACTION_SIZE, np.float32), np.ones(ACTION_SIZE, np.float32),
                                           dtype=np.float32)
        self._values = np.zeros(self.distractors.count)
        self._steps = 0

    @property
    def factor_names(self) -> tuple[str, ...]:
        return self.scene_names + self.distractors.names

    @property
    def global_graph(self) -> np.ndarray:
        """uint8 ``[d, d + 1]`` (read-only): the dense scene block (module docstring) and the distractors."""
        return self._global_graph

    @property
    def reward_parents(self) -> np.ndarray:
        """uint8 ``[d + 1]``: every scene factor and the action (the reward reads the scene at t+1)."""
        parents = np.r_[np.ones(len(self.scene_names)), np.zeros(self.distractors.count), 1]
        return parents.astype(np.uint8)

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        # the suite's task draws its initial state from its own generator: seed it from ours
        self._env.task.random.seed(int(self.np_random.integers(2**31)))
        time_step = self._env.reset()
        self._values = self.distractors.reset(self.np_random)
        self._steps = 0
        return self._observation(time_step), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(ACTION_SIZE), -1.0, 1.0)
        time_step = self._env.step(a)
        self._values = self.distractors.step(a, self.np_random)
        self._steps += 1
        truncated = self._steps >= self.episode_length or time_step.last()
        return self._observation(time_step), float(time_step.reward or 0.0), False, truncated, {}

    def env_spec(self) -> EnvSpec:
        """Factors (continuous, normalised by the random policy's statistics; distractors scale 1), the
        6-D continuous action, the truth of the module docstring and the reward's parents."""
        m = self.distractors.count
        locs, scales = _NORMALISATION[self.DOMAIN]
        return EnvSpec(
            env_id=self.ENV_ID, factor_names=self.factor_names,
            factor_kinds=("continuous",) * len(self.factor_names), factor_sizes=(1,) * len(self.factor_names),
            factor_objects=tuple(n.split(".")[0] for n in self.scene_names) + self.distractors.objects,
            factor_locs=tuple(locs) + (0.0,) * m, factor_scales=tuple(scales) + (1.0,) * m,
            action_kind="continuous", action_size=ACTION_SIZE, episode_length=self.episode_length,
            global_graph=self._global_graph.copy(), reward_parents=self.reward_parents,
            config_json=json.dumps(self.config()),
        )

    def config(self) -> dict[str, Any]:
        d = self.distractors
        return {"task": self.task, "distractors": f"{d.controllable},{d.uncontrollable}",
                "distractor_seed": self.distractor_seed, "episode_length": self.episode_length,
                **({"distractor_ood": list(d.ood_range)} if d.ood_range else {})}

    def _observation(self, time_step: Any) -> np.ndarray:
        scene = np.concatenate([np.atleast_1d(v) for v in time_step.observation.values()])
        return np.concatenate([scene, self._values]).astype(np.float32)


class WalkerEnv(DMCEnv):
    DOMAIN, ENV_ID = "walker", "dmc-walker"


class CheetahEnv(DMCEnv):
    DOMAIN, ENV_ID = "cheetah", "dmc-cheetah"


def _scene_names(domain: str, physics: Any) -> tuple[str, ...]:
    """Factor names of the suite's observation, in its order (see the module docstring)."""
    model = physics.model
    bodies = [model.id2name(i, "body") for i in range(1, model.nbody)]
    joints = [model.id2name(i, "joint") for i in range(model.njnt)]
    if domain == "walker":
        return (tuple(f"{b}.{c}" for b in bodies for c in ("xx", "xz")) + ("height",)
                + tuple(f"{j}.vel" for j in joints))
    return tuple(f"{j}.pos" for j in joints[1:]) + tuple(f"{j}.vel" for j in joints)
