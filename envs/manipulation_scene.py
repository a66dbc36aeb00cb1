"""The robosuite 1.5 scene behind :class:`envs.manipulation.ManipulationEnv` (dissertation 3.3.1).

A UR5e arm with a parallel two-finger gripper at a table; on the table a free-jointed movable cube
``mov`` and two *kinematic* cubes, ``unm`` (never moved) and ``rand`` (moved by a random walk), plus
three visual-only markers. ``unm``, ``rand`` and the markers are MuJoCo mocap bodies: their poses are
set, never integrated, so no contact can move them; the markers' geoms have ``contype = conaffinity
= 0``. Mocap bodies are welded to the world for collision filtering, so ``unm`` and ``rand`` pass
through each other and the table instead of fighting over it.

The gripper is Franka's (robosuite's ``PandaGripper`` model) mounted on the UR5e, not the UR5e's
default Robotiq 85: robosuite 1.5's Robotiq 85 couples its six finger joints only through soft
tendons, so its pads tilt under load and squeeze a 4 cm cube out (every scripted grasp failed, and
opening the fingers at full speed flung a touching cube 20 cm). The parallel gripper grasps
reliably, and its two slide joints are the chapter's two gripper coordinates.

This module knows robosuite; the gymnasium environment, its factors and its ground truth do not. The
scene is stepped through robosuite's own ``step`` (controller at 500 Hz, policy at ``control_freq``),
and records which bodies touched during every physics sub-step of a policy step. Per sub-step, the
arm's torques come from :class:`envs.manipulation_control.OSCPositionTorques` (robosuite's formula,
bit-for-bit, without its generic call chain) and contacts are only marked by geom pair; they are
turned into body classes once per policy step. Together with no observables, that makes a step
about 2x faster than robosuite's own path with identical trajectories.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from collections import OrderedDict
from typing import Any

import mujoco
import numpy as np
from robosuite.controllers import load_composite_controller_config
from robosuite.environments.manipulation.manipulation_env import ManipulationEnv as RobosuiteManipulationEnv
from robosuite.models.arenas import TableArena
from robosuite.models.grippers import register_gripper
from robosuite.models.grippers.panda_gripper import PandaGripperBase
from robosuite.models.objects import BoxObject, CompositeObject
from robosuite.models.tasks import ManipulationTask

from envs.manipulation_control import OSCPositionTorques
from envs.manipulation_layout import (
    BOX_HEIGHT, BOX_INNER_HALF, BOX_WALL, FIXED_HALF, MANIPULATION, MARKER_RADIUS, MOV_HALF, TABLE_SIZE,
    TABLE_TOP, TOOL_HANDLE_HALF, TOOL_HOOK_CENTRE, TOOL_HOOK_HALF, SceneLayout,
)

GRIPPER_JOINTS = ("finger_joint1", "finger_joint2")
_MOVABLE_RGBA = ([1, 0, 0, 1], [1, 0.5, 0, 1], [0.8, 0, 0.8, 1], [1, 1, 0, 1])
_KINEMATIC_RGBA = {"unm": [0, 0.8, 0, 1], "rand": [0, 0, 1, 1]}
"""The two finger joints of the parallel gripper: the chapter's two gripper joints."""


@register_gripper
class OpeningPandaGripper(PandaGripperBase):
    """Franka's parallel gripper commanded by one scalar in [-1, 1] (-1 open, 1 closed), mapped
    proportionally onto both fingers' position targets. robosuite's ``PandaGripper`` integrates the
    action's *sign*, a hidden state that cannot express the chapter's "degree to which the gripper
    is opened"."""

    def format_action(self, action: np.ndarray) -> np.ndarray:
        return np.array([-action[0], action[0]])

    @property
    def dof(self) -> int:
        return 1


class CausalTableScene(RobosuiteManipulationEnv):
    """The table scene. The arm runs robosuite's OSC_POSITION controller with *absolute* world-frame
    goals and a fixed orientation goal (see :meth:`reset_scene`); the gripper takes one scalar.

    ``layout`` says which cubes and markers the table holds (chapter 3's scene by default, chapter 4's
    block scene: :data:`envs.manipulation_layout.BLOCK`). :meth:`step_to` advances one policy step;
    :attr:`contacts` is then the symmetric boolean matrix over ``layout.contact_groups`` (``[5, 5]``
    in chapter 3's scene) of the body classes that touched in any sub-step, and the kinematic bodies
    have moved linearly from their old to their new targets over the step.
    """

    def __init__(self, *, robot: str = "UR5e", control_freq: int = 10, layout: SceneLayout = MANIPULATION) -> None:
        controller = load_composite_controller_config(robot=robot)
        # robosuite 1.5.2 does not implement OSC position_limits (it raises), and a "delta" OSC_POSITION
        # re-reads the achieved orientation as its goal every step (so it drifts under contact). We send
        # absolute goals (clipped to the workspace by the caller) in "desired" mode: the orientation goal
        # then stays the one the arm started with.
        controller["body_parts"]["right"].update(type="OSC_POSITION", input_type="absolute", input_ref_frame="world")
        self.layout = layout
        self.contacts = np.zeros((len(layout.contact_groups),) * 2, dtype=bool)
        self._kinematic_from = self._kinematic_path = np.zeros((0, 3))
        self._substep = 0
        self.robosuite_controller = False
        """True: run robosuite's generic per-sub-step controller path instead of
        :class:`envs.manipulation_control.OSCPositionTorques` (the same torques, half the speed; the
        tests' reference)."""
        super().__init__(
            robots=robot,
            controller_configs=controller,
            gripper_types="OpeningPandaGripper",
            initialization_noise=None,
            use_camera_obs=False,
            has_renderer=False,
            has_offscreen_renderer=False,
            control_freq=control_freq,
            horizon=2**31 - 1,
            ignore_done=True,
            hard_reset=False,
        )
        self._find_ids()
        self._prepare_substeps()

    # ------------------------------------------------------------------ robosuite hooks

    def _load_model(self) -> None:
        super()._load_model()
        robot_model = self.robots[0].robot_model
        robot_model.set_base_xpos(robot_model.base_xpos_offset["table"](TABLE_SIZE[0]))
        arena = TableArena(table_full_size=TABLE_SIZE, table_offset=TABLE_TOP)
        arena.set_origin([0, 0, 0])
        self.movables = [_body(name, self.layout.shape(name), _MOVABLE_RGBA[k % len(_MOVABLE_RGBA)], "default")
                         for k, name in enumerate(self.layout.movable)]
        self.kinematics = [_body(name, self.layout.shape(name), _KINEMATIC_RGBA.get(name, [0.5] * 3 + [1]), None)
                           for name in self.layout.kinematic]
        for kinematic in self.kinematics:
            kinematic.get_obj().set("mocap", "true")
        for name in self.layout.markers:
            body = ET.SubElement(arena.worldbody, "body", name=name, mocap="true", pos="0 0 -1")
            ET.SubElement(body, "geom", name=f"{name}_g", type="cylinder", size=f"{MARKER_RADIUS} 0.001",
                          rgba="0 0 0 1", contype="0", conaffinity="0", group="1")
        self.model = ManipulationTask(mujoco_arena=arena, mujoco_robots=[robot_model],
                                      mujoco_objects=[*self.movables, *self.kinematics])

    def _setup_observables(self) -> OrderedDict:
        return OrderedDict()  # the gymnasium env reads the simulator directly; this saves ~10% per step

    def reward(self, action: Any = None) -> float:
        return 0.0

    def _pre_action(self, action: np.ndarray, policy_step: bool = False) -> None:
        if self.robosuite_controller:
            super()._pre_action(action, policy_step)
        else:
            self._control(action, policy_step)
        contact = self._data.contact.geom  # this sub-step's contacts (mj_step1 ran collision detection)
        self._touched[contact[:, 0], contact[:, 1]] = True
        self._substep += 1
        frac = min(self._substep / self._substeps, 1.0)
        self._data.mocap_pos[self.kinematic_mocap] = self._kinematic_from + frac * self._kinematic_path

    # ------------------------------------------------------------------ what the gym env calls

    def reset_scene(self) -> None:
        """robosuite's soft reset (robot at its initial joints), then the arm's goal mode pinned."""
        self.reset()
        self.robots[0].part_controllers["right"].set_goal_update_mode("desired")
        self.contacts[:] = False
        self.eef_rest_xmat = self._data.site_xmat[self.robots[0].eef_site_id["right"]].reshape(3, 3).copy()

    def commit_poses(self) -> None:
        """Make a state just written into the simulator (poses, a restored snapshot) take effect."""
        self.sim.forward()
        for controller in self.robots[0].part_controllers.values():
            controller.new_update = True  # else the first step reuses the arm state cached before the write
        self._kinematic_from = self.kinematic_pos()
        self._kinematic_path = np.zeros_like(self._kinematic_from)

    def step_to(self, goal: np.ndarray, grip: float, kinematic_targets: np.ndarray) -> None:
        """One policy step towards eef ``goal`` (world xyz) with gripper command ``grip`` in [-1, 1],
        while the kinematic bodies (``unm``, ``rand``, markers, in that order) glide to their targets."""
        self._touched[:] = False
        self._substep = 0
        self._kinematic_from = self.sim.data.mocap_pos[self.kinematic_mocap].copy()
        self._kinematic_path = np.asarray(kinematic_targets, dtype=np.float64) - self._kinematic_from
        self.step(np.concatenate([goal, [grip]]))
        self._collect_contacts()

    def eef_pos(self) -> np.ndarray:
        return self.sim.data.site_xpos[self.robots[0].eef_site_id["right"]].copy()

    def gripper_qpos(self) -> np.ndarray:
        return self.sim.data.qpos[self.gripper_qpos_addr].copy()

    def eef_vel(self) -> np.ndarray:
        """World-frame linear velocity (m/s) of the end-effector site: its Jacobian times ``qvel``."""
        return self._eef_jacobian(linear=True) @ self._data.qvel

    def eef_rotation(self) -> np.ndarray:
        """The end-effector's orientation as a rotation vector (axis x angle, radians, in the world's
        frame) from its orientation at reset, which the controller's fixed orientation goal holds only
        approximately (so it is state, and without it the arm is not Markov in its factors)."""
        deviation = self._data.site_xmat[self.robots[0].eef_site_id["right"]].reshape(3, 3) @ self.eef_rest_xmat.T
        quat, rotvec = np.zeros(4), np.zeros(3)
        mujoco.mju_mat2Quat(quat, deviation.ravel())
        mujoco.mju_quat2Vel(rotvec, quat, 1.0)
        return rotvec

    def eef_angular_vel(self) -> np.ndarray:
        """World-frame angular velocity (rad/s) of the end-effector site."""
        return self._eef_jacobian(linear=False) @ self._data.qvel

    def _eef_jacobian(self, *, linear: bool) -> np.ndarray:
        """``[3, nv]``: the end-effector site's translational (``linear``) or rotational Jacobian."""
        m = self.sim.model._model
        jac = np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, self._data, jac if linear else None, None if linear else jac,
                          self.robots[0].eef_site_id["right"])
        return jac

    def gripper_qvel(self) -> np.ndarray:
        """Velocities (m/s) of the two finger slide joints."""
        return self.sim.data.qvel[self.gripper_qvel_addr].copy()

    def mov_vel(self, k: int = 0) -> np.ndarray:
        """World-frame linear velocity (m/s) of movable body ``k`` (its free joint's first three)."""
        v = self.mov_qvel_addr[k]
        return self.sim.data.qvel[v:v + 3].copy()

    def mov_yaw_rate(self, k: int = 0) -> float:
        """Angular velocity (rad/s) of movable body ``k`` about the world's vertical (a free joint's
        angular velocity is in the body's frame: rotated to the world's by the body's quaternion)."""
        v, world = self.mov_qvel_addr[k], np.zeros(3)
        mujoco.mju_rotVecQuat(world, self.sim.data.qvel[v + 3:v + 6], self.mov_quat(k))
        return float(world[2])

    def mov_pos(self, k: int = 0) -> np.ndarray:
        """Position of movable cube ``k`` (``mov`` in chapter 3's scene)."""
        a = self.mov_qpos_addr[k]
        return self.sim.data.qpos[a:a + 3].copy()

    def movable_pos(self) -> np.ndarray:
        """``[M, 3]`` positions of the movable cubes."""
        return np.stack([self.mov_pos(k) for k in range(len(self.layout.movable))])

    def mov_yaw(self, k: int = 0) -> float:
        """Rotation (radians, (-pi, pi]) of movable body ``k`` about the vertical: the yaw of its quaternion."""
        w, x, y, z = self.mov_quat(k)
        return float(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))

    def mov_quat(self, k: int = 0) -> np.ndarray:
        a = self.mov_qpos_addr[k]
        return self.sim.data.qpos[a + 3:a + 7].copy()

    def set_mov_pose(self, pos: np.ndarray, quat: np.ndarray, k: int = 0) -> None:
        """Place movable cube ``k`` (quat is w, x, y, z) at rest."""
        a, v = self.mov_qpos_addr[k], self.mov_qvel_addr[k]
        self.sim.data.qpos[a:a + 7] = np.concatenate([pos, quat])
        self.sim.data.qvel[v:v + 6] = 0.0

    def kinematic_pos(self) -> np.ndarray:
        """``[K, 3]`` positions of the kinematic bodies (``layout.mocap``: in chapter 3's scene ``unm``,
        ``rand``, ``mk1``, ``mk2``, ``mk3``)."""
        return self.sim.data.mocap_pos[self.kinematic_mocap].copy()

    def set_kinematic_pose(self, pos: np.ndarray, quat: np.ndarray | None = None) -> None:
        self.sim.data.mocap_pos[self.kinematic_mocap] = pos
        if quat is not None:
            self.sim.data.mocap_quat[self.kinematic_mocap] = quat

    # ------------------------------------------------------------------ internals

    def _find_ids(self) -> None:
        m = self.sim.model._model
        prefix = self.robots[0].gripper["right"].naming_prefix
        joints = [m.joint(prefix + j).id for j in GRIPPER_JOINTS]
        self.gripper_qpos_addr = m.jnt_qposadr[joints]
        self.gripper_qvel_addr = m.jnt_dofadr[joints]
        joints = [m.joint(cube.joints[0]).id for cube in self.movables]
        self.mov_qpos_addr = [int(m.jnt_qposadr[j]) for j in joints]
        self.mov_qvel_addr = [int(m.jnt_dofadr[j]) for j in joints]
        bodies = [cube.root_body for cube in self.kinematics] + list(self.layout.markers)
        self.kinematic_mocap = np.array([m.body_mocapid[m.body(b).id] for b in bodies])
        cubes = [cube.root_body for cube in (*self.movables, *self.kinematics)]
        self.geom_group = _geom_groups(m, self.robots[0].robot_model.root_body, cubes)

    def _prepare_substeps(self) -> None:
        """What every physics sub-step uses, resolved once."""
        m, robot = self.sim.model._model, self.robots[0]
        self._data = self.sim.data._data
        self._substeps = round(self.control_timestep / self.model_timestep)
        self._touched = np.zeros((m.ngeom, m.ngeom), dtype=bool)
        """Geom pairs (MuJoCo's order) in contact in any sub-step of the current policy step."""
        actuators = robot._ref_actuators_indexes_dict
        self._arm_actuators, self._gripper_actuators = actuators["right"], actuators["right_gripper"]
        self._gripper_range = m.actuator_ctrlrange[self._gripper_actuators]
        self._arm = robot.part_controllers["right"]
        self._arm_torques = OSCPositionTorques(self._arm, m.actuator_ctrlrange[self._arm_actuators])

    def _control(self, action: np.ndarray, policy_step: bool) -> None:
        """robosuite's ``Robot.control`` for this robot, less its unused proprioceptive buffers: goals
        are set by robosuite's controllers at the policy step; the gripper's command is then fixed
        for the step (no interpolator), the arm's torques are evaluated every sub-step."""
        if policy_step:
            robot = self.robots[0]
            robot.composite_controller.update_state()
            robot.composite_controller.set_goal(action)
            self._arm = robot.part_controllers["right"]  # robosuite builds new controllers on reset
            self._arm.new_update = True  # as its run_controller would leave it
            gripper = robot.part_controllers["right_gripper"]
            self._data.ctrl[self._gripper_actuators] = np.clip(gripper.run_controller(), *self._gripper_range.T)
        self._data.ctrl[self._arm_actuators] = self._arm_torques.torques(self._arm)

    def _collect_contacts(self) -> None:
        """:attr:`contacts` from the geom pairs that touched during the step, in one pass."""
        first, second = np.nonzero(self._touched)
        groups = self.geom_group
        self.contacts[:] = False
        self.contacts[groups[first], groups[second]] = True
        self.contacts[groups[second], groups[first]] = True


def _body(name: str, shape: str, rgba: list[float], joints: Any) -> Any:
    """A cube (``mov*``: half-size :data:`MOV_HALF`; kinematic: :data:`FIXED_HALF`), the L-shaped tool
    (handle along its x axis, hook across the far end towards -y; origin at the handle's centre) or
    the open box (a floor and four walls; origin at the floor's centre)."""
    if shape == "cube":
        return BoxObject(name, size=[MOV_HALF if joints else FIXED_HALF] * 3, rgba=rgba, joints=joints)
    if shape == "l-tool":
        hx, hy, hz = TOOL_HANDLE_HALF
        return CompositeObject(
            name, total_size=[hx, hy, hz], geom_types=["box", "box"], geom_sizes=[TOOL_HANDLE_HALF, TOOL_HOOK_HALF],
            geom_locations=[(0.0, 0.0, 0.0), (*TOOL_HOOK_CENTRE, 0.0)], geom_names=["handle", "hook"],
            rgba=rgba, density=500.0, locations_relative_to_center=True, joints=joints,
            geom_frictions=[(1.0, 0.005, 0.0001)] * 2)
    if shape == "open-box":
        inner, wall, height = BOX_INNER_HALF, BOX_WALL, BOX_HEIGHT
        outer = inner + 2 * wall
        sizes = [(outer, outer, wall)] + [(wall, outer, height), (wall, outer, height),
                                          (inner, wall, height), (inner, wall, height)]
        places = [(0.0, 0.0, 0.0)] + [(s * (inner + wall), 0.0, height) for s in (-1, 1)] + [
            (0.0, s * (inner + wall), height) for s in (-1, 1)]
        return CompositeObject(
            name, total_size=[outer, outer, height + wall], geom_types=["box"] * 5, geom_sizes=sizes,
            geom_locations=places, geom_names=["floor", "wall0", "wall1", "wall2", "wall3"], rgba=rgba,
            locations_relative_to_center=True, joints=joints)
    raise ValueError(f"unknown body shape {shape!r}")


def _geom_groups(m: Any, robot_root: str, cubes: list[str]) -> np.ndarray:
    """Contact group of every geom: the moving links of the robot (0; its pedestal and base, welded
    to the world, always touch the floor and are static scenery), the cubes (1, 2, ... in order), the
    static rest (last)."""
    groups = np.full(m.ngeom, len(cubes) + 1, dtype=np.int64)
    body = m.geom_bodyid
    robot = (m.body_rootid[body] == m.body(robot_root).id) & (m.body_weldid[body] != 0)
    groups[robot] = 0
    for group, name in enumerate(cubes, start=1):
        groups[body == m.body(name).id] = group
    return groups
