"""The manipulation environment of CDL (dissertation chapter 3.3.1) on robosuite 1.5.

A UR5e arm with a parallel gripper at a table with a movable cube ``mov``, a cube ``unm`` fixed to
the table, a cube ``rand`` that moves by a random walk and that nothing else can move, and three
random-walking markers that nothing can touch. Cubes and markers start at random places on the
table every episode. The state is 23 one-dimensional factors, the action a 4-D end-effector
displacement and gripper opening at 10 Hz; episodes last 250 steps. The ground truth is derived and
justified in :mod:`envs.manipulation_truth`; the robosuite scene lives in :mod:`envs.manipulation_scene`.

The chapter ran a custom robosuite 1.3 fork that does not run on 1.5; this is a re-implementation of
the scene it describes, not a port of its code.
"""
from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from typing import Any, Mapping

import gymnasium as gym
import mujoco
import numpy as np

from envs.manipulation_layout import (
    FIXED_HALF, MANIPULATION, MOV_HALF, REGION_HIGH, REGION_LOW, TABLE_TOP, WORKSPACE_HIGH, WORKSPACE_LOW,
    SceneLayout,
)
from envs.manipulation_scene import CausalTableScene
from envs.manipulation_truth import global_graph, local_graph
from proto.messages import EnvSpec

ROBOTS = ("UR5e", "Panda")
"""Arms the scene is built for (both carry the same parallel gripper); UR5e is the chapter's."""
POSITION_BOUND = 10.0
"""Observation-space bound on every factor, far outside the scene (a dropped cube lies on the floor)."""
MIN_CUBE_SEPARATION = 0.09
"""Minimum distance between cube centres at reset, so that no episode starts with cubes touching."""
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
_UPRIGHT = np.array([1.0, 0.0, 0.0, 0.0])
"""Cubes start axis-aligned: orientation is not part of the state, so a random yaw would be a hidden
variable of every contact (and a parallel gripper that cannot turn cannot hold a cube by its edges)."""


@dataclass(frozen=True)
class ManipulationSnapshot:
    """Everything that decides the rest of an episode: the simulator's full integration state, the
    environment's random generator (it drives the random walks) and the step count."""

    physics: np.ndarray
    rng_state: dict[str, Any]
    steps: int


class ManipulationEnv(gym.Env[np.ndarray, np.ndarray]):
    """The manipulation scene as a factored gymnasium environment.

    Observation: float32 ``[23]`` in the order of :attr:`factor_names` (``eef.x .. eef.z``,
    ``grp.0``, ``grp.1``, then ``x, y, z`` of ``mov``, ``unm``, ``rand``, ``mk1``-``mk3``), in world
    metres (the two finger joints are slides: ``grp.0`` in [0, 0.04], ``grp.1`` in
    [-0.04, 0], open at the extremes). Action: float32 ``[4]``; ``a[:3]`` in [-1, 1] moves the
    end-effector goal by ``max_displacement * a[:3]`` metres from where it is (clipped to the
    workspace), ``a[3]`` in [0, 1] is how far the gripper is opened (0 closed, 1 open). Reward 0;
    episodes never terminate and truncate after ``episode_length`` steps.

    ``info["local_graph"]`` is the uint8 ``[23, 24]`` graph of the step from the contacts the
    simulator reported during it; :attr:`global_graph` is the one-step ground truth. ``rand`` and the
    markers move by ``U(-random_walk_step, random_walk_step)`` per axis and step, clipped to the table
    area. Every random choice comes from ``self.np_random``, so ``reset(seed=s)`` fixes the episode.

    ``velocities=True`` adds velocity factors after the positions (14 in this scene: ``eef.vx/vy/vz``
    in m/s, the end-effector's orientation ``eef.rx/ry/rz`` and angular velocity ``eef.wx/wy/wz``,
    ``grp.v0/v1``, ``mov.vx/vy/vz``; :meth:`envs.manipulation_layout.SceneLayout.with_velocities`),
    which make the state Markov (the chapter's state is not: the arm's velocity and the orientation
    its controller holds only approximately are hidden; see docs/environments.md). Each belongs to
    its body's block of the ground truth. Not the chapter's state: off by default.
    """

    metadata = {"render_modes": []}
    LAYOUT: SceneLayout = MANIPULATION
    """The cubes and markers on the table (a subclass sets another: :class:`envs.block.BlockEnv`)."""
    ENV_ID = "manipulation"

    def __init__(
        self,
        *,
        episode_length: int = 250,
        max_displacement: float = 0.03,
        random_walk_step: float = 0.01,
        control_freq: int = 10,
        robot: str = "UR5e",
        velocities: bool = False,
        render_mode: str | None = None,
    ) -> None:
        _check_config(episode_length, max_displacement, random_walk_step, control_freq, robot, render_mode)
        self.episode_length, self.max_displacement = episode_length, max_displacement
        self.random_walk_step, self.control_freq, self.robot = random_walk_step, control_freq, robot
        self.render_mode, self.velocities = render_mode, bool(velocities)
        self.layout = self.LAYOUT.with_velocities() if velocities else self.LAYOUT
        self.scene = CausalTableScene(robot=robot, control_freq=control_freq, layout=self.layout)
        self.action_space = gym.spaces.Box(
            np.array([-1, -1, -1, 0], np.float32), np.ones(4, np.float32), dtype=np.float32
        )
        bound = np.full(self.layout.num_factors, POSITION_BOUND, np.float32)
        self.observation_space = gym.spaces.Box(-bound, bound, dtype=np.float32)
        self._global_graph = global_graph(self.layout)
        self._global_graph.flags.writeable = False
        self._steps = 0

    @property
    def global_graph(self) -> np.ndarray:
        """uint8 ``[23, 24]`` one-step ground truth (read-only), see :mod:`envs.manipulation_truth`."""
        return self._global_graph

    @property
    def factor_names(self) -> tuple[str, ...]:
        return self.layout.factor_names

    def constant_factors(self) -> tuple[str, ...]:
        """Factors constant in every episode by construction (:data:`envs.manipulation_layout.CONSTANT_FACTORS`):
        the edges they cause are true but cannot be learned from this environment's data."""
        return self.layout.constant_factors

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """The arm at its start pose, gripper open; cubes and markers at random places on the table."""
        super().reset(seed=seed)
        self.scene.reset_scene()
        lay = self.layout
        cubes = self._sample_cube_xy()
        markers = self.np_random.uniform(REGION_LOW, REGION_HIGH, size=(len(lay.markers), 2))
        for k in range(len(lay.movable)):
            self.scene.set_mov_pose(np.r_[cubes[k], TABLE_TOP[2] + MOV_HALF], _UPRIGHT, k)
        heights = np.r_[[TABLE_TOP[2] + FIXED_HALF] * len(lay.kinematic), [TABLE_TOP[2]] * len(lay.markers)]
        kinematic_xy = np.vstack([cubes[len(lay.movable):], markers])
        self.scene.set_kinematic_pose(np.column_stack([kinematic_xy, heights]), np.tile(_UPRIGHT, (len(heights), 1)))
        self.scene.commit_poses()
        self._steps = 0
        return self._observation(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move the arm and gripper for one control period while ``rand`` and the markers walk."""
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(4), self.action_space.low, self.action_space.high)
        goal = np.clip(self.scene.eef_pos() + self.max_displacement * a[:3], WORKSPACE_LOW, WORKSPACE_HIGH)
        self.scene.step_to(goal, 1.0 - 2.0 * a[3], self._walk())
        self._steps += 1
        info = {"local_graph": local_graph(self.scene.contacts, self.layout)}
        return self._observation(), 0.0, False, self._steps >= self.episode_length, info

    # ------------------------------------------------------------------ interventions

    def snapshot(self) -> ManipulationSnapshot:
        """The current state of the episode, to :meth:`restore` later (interventions, planning)."""
        m, d = self.scene.sim.model._model, self.scene.sim.data._data
        physics = np.empty(mujoco.mj_stateSize(m, _STATE))
        mujoco.mj_getState(m, d, physics, _STATE)
        return ManipulationSnapshot(physics, copy.deepcopy(self.np_random.bit_generator.state), self._steps)

    def restore(self, snapshot: ManipulationSnapshot) -> np.ndarray:
        """Return to ``snapshot`` (taken from this environment) and give its observation."""
        mujoco.mj_setState(self.scene.sim.model._model, self.scene.sim.data._data, snapshot.physics, _STATE)
        self.scene.commit_poses()
        self.np_random.bit_generator.state = copy.deepcopy(snapshot.rng_state)
        self._steps = snapshot.steps
        return self._observation()

    def intervene(self, values: Mapping[str, float]) -> np.ndarray:
        """Set factors by name (``{"mk1.x": 0.1, "unm.y": -0.05}``) and give the new observation.

        Cube, tool (``tool.yaw`` too) and marker coordinates and ``grp.*`` can be set; ``eef.*`` cannot (it is the arm's
        forward kinematics: move it with actions). Everything not named keeps its exact state (a
        set movable cube is also put at rest). A cube set into another body is pushed out by the
        simulator on the next step.
        """
        scene, lay = self.scene, self.layout
        grp, movable, kinematic = scene.gripper_qpos(), scene.movable_pos(), scene.kinematic_pos()
        touched, yaws = set(), {}
        settable = tuple(n for n in lay.factor_names if not n.startswith("eef.") and n.split(".")[1][0] != "v")
        for name, value in values.items():
            if name not in settable:
                raise KeyError(f"cannot intervene on {name!r}; settable: {settable}")
            obj, dim = name.split(".")
            if dim == "yaw":
                yaws[obj] = float(value)
                touched.add(obj)
                continue
            if obj == "grp":
                row = grp
            elif obj in lay.movable:
                row = movable[lay.movable.index(obj)]
            else:
                row = kinematic[lay.mocap.index(obj)]
            row[lay.dims(obj).index(dim)] = value
            touched.add(obj)
        if "grp" in touched:
            scene.sim.data.qpos[scene.gripper_qpos_addr] = grp
        for k, obj in enumerate(lay.movable):
            if obj in touched:
                quat = yaw_quat(yaws[obj]) if obj in yaws else scene.mov_quat(k)
                scene.set_mov_pose(movable[k], quat, k)
        scene.set_kinematic_pose(kinematic)
        scene.commit_poses()
        return self._observation()

    # ------------------------------------------------------------------ spec

    def env_spec(self) -> EnvSpec:
        """The factor layout, action space, ground truth and configuration, as the bus carries it.
        Normalisation: positions about a point 5 cm above the table's centre, 0.1 m per unit;
        finger joints about mid-range, 0.02 m per unit (so each spans [-1, 1]); velocities (if
        any) about 0, 0.1 m/s or rad/s per unit (a tool's yaw rate 1 rad/s), the end-effector's
        orientation 0.01 rad per unit."""
        n = self.layout.num_factors
        locs, scales = _normalisation(self.layout)
        return EnvSpec(
            env_id=self.ENV_ID,
            factor_names=self.layout.factor_names,
            factor_kinds=("continuous",) * n,
            factor_sizes=(1,) * n,
            factor_objects=self.layout.factor_objects,
            factor_locs=locs,
            factor_scales=scales,
            action_kind="continuous",
            action_size=4,
            episode_length=self.episode_length,
            global_graph=self._global_graph.copy(),
            config_json=json.dumps(self.config()),
        )

    def config(self) -> dict[str, Any]:
        """The constructor arguments (JSON-ready)."""
        return {
            "episode_length": self.episode_length,
            "max_displacement": self.max_displacement,
            "random_walk_step": self.random_walk_step,
            "control_freq": self.control_freq,
            "robot": self.robot,
            "velocities": self.velocities,
        }

    def close(self) -> None:
        self.scene.close()

    # ------------------------------------------------------------------ internals

    def _sample_cube_xy(self) -> np.ndarray:
        cubes = len(self.layout.movable) + len(self.layout.kinematic)
        while True:
            xy = self.np_random.uniform(REGION_LOW, REGION_HIGH, size=(cubes, 2))
            gaps = np.linalg.norm(xy[:, None] - xy[None], axis=-1)[np.triu_indices(cubes, 1)]
            if gaps.min() >= MIN_CUBE_SEPARATION:
                return xy

    def _walk(self) -> np.ndarray:
        """Targets of the kinematic bodies for this step: ``unm`` stays, the others walk per axis."""
        pos = self.scene.kinematic_pos()
        walking = np.array([name not in self.layout.still for name in self.layout.mocap], dtype=bool)
        step = self.np_random.uniform(-self.random_walk_step, self.random_walk_step, size=(int(walking.sum()), 2))
        pos[walking, :2] = np.clip(pos[walking, :2] + step, REGION_LOW, REGION_HIGH)
        return pos

    def _observation(self) -> np.ndarray:
        s = self.scene
        movable = [np.r_[s.mov_pos(k), [s.mov_yaw(k)] if name in self.layout.oriented else []]
                   for k, name in enumerate(self.layout.movable)]
        parts = [s.eef_pos(), s.gripper_qpos(), *movable, s.kinematic_pos().ravel()]
        if self.layout.velocities:
            parts += [s.eef_vel(), s.eef_rotation(), s.eef_angular_vel(), s.gripper_qvel()]
            parts += [np.r_[s.mov_vel(k), [s.mov_yaw_rate(k)] if name in self.layout.oriented else []]
                      for k, name in enumerate(self.layout.movable)]
        return np.concatenate(parts).astype(np.float32)


def yaw_quat(yaw: float) -> np.ndarray:
    """The (w, x, y, z) quaternion of a rotation by ``yaw`` radians about the vertical."""
    return np.array([np.cos(yaw / 2.0), 0.0, 0.0, np.sin(yaw / 2.0)])


def _normalisation(layout: SceneLayout) -> tuple[tuple[float, ...], tuple[float, ...]]:
    centre = {"x": TABLE_TOP[0], "y": TABLE_TOP[1], "z": TABLE_TOP[2] + 0.05, "0": 0.02, "1": -0.02, "yaw": 0.0}
    scale = {"0": 0.02, "1": 0.02, "yaw": 1.0}
    dims = [name.split(".")[1] for name in layout.factor_names]
    # Velocities about 0, 0.1 m/s or rad/s per unit (1 rad/s for a tool's yaw), the end-effector's
    # orientation 0.01 rad per unit: under uniformly random actions the end-effector's and fingers'
    # speeds have a standard deviation of 0.06 m/s, its angular velocity 0.03-0.1 rad/s, its
    # orientation's deviation 0.003-0.011 rad.
    scale |= {"vyaw": 1.0, "rx": 0.01, "ry": 0.01, "rz": 0.01}
    dynamic = ("v", "r", "w")  # no position dimension starts with these
    return (tuple(0.0 if d[0] in dynamic else float(centre[d]) for d in dims), tuple(scale.get(d, 0.1) for d in dims))


def _check_config(
    episode_length: int, max_displacement: float, random_walk_step: float, control_freq: int, robot: str,
    render_mode: str | None,
) -> None:
    if episode_length < 1:
        raise ValueError(f"episode_length must be >= 1, got {episode_length}")
    if not 0 < max_displacement <= 0.1:
        raise ValueError(f"max_displacement must be in (0, 0.1] metres, got {max_displacement}")
    if not random_walk_step >= 0:
        raise ValueError(f"random_walk_step must be >= 0, got {random_walk_step}")
    if control_freq < 1 or 500 % control_freq:
        raise ValueError(f"control_freq must divide the 500 Hz physics rate, got {control_freq}")
    if robot not in ROBOTS:
        raise ValueError(f"robot must be one of {ROBOTS}, got {robot!r}")
    if render_mode is not None:
        raise ValueError(f"render_mode must be None (no renderer), got {render_mode!r}")
