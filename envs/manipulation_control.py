"""The arm's operational-space torques of the manipulation scene, computed straight from MjData.

robosuite runs its controller at the physics rate (500 Hz, 50 sub-steps per 10 Hz policy step), and
its generic path (robot -> composite controller -> part controller, name lookups, four Jacobian
calls, three action-limit rebuilds, proprioceptive buffers) took three quarters of a step's
time. :class:`OSCPositionTorques` evaluates the
same formula as robosuite 1.5.2's ``OperationalSpaceController.run_controller`` for the one
configuration the scene uses (position-only OSC, absolute world-frame goal, fixed impedance,
uncoupled position and orientation, no interpolator, fixed base) with the same numpy and numba
calls in the same order, so the torques -- and hence every trajectory -- are bit-for-bit robosuite's
(``tests/envs/test_manipulation.py`` runs both side by side). Goals are still set by robosuite's
controller (``set_goal``); this class only replaces the per-sub-step evaluation. (Fusing it all
into one numba function halves its cost again, but numba's BLAS rounds differently from numpy's,
and 1e-14 differences in torque grow into different contact trajectories.)
"""
from __future__ import annotations

from typing import Any

import mujoco
import numpy as np
from robosuite.utils.control_utils import nullspace_torques, opspace_matrices, orientation_error


class OSCPositionTorques:
    """Per-sub-step torques of a robosuite ``OperationalSpaceController``, clipped to the arm
    actuators' control range like robosuite's ``Robot.control``. ``controller`` (checked to be a
    supported configuration) fixes the simulator, site and joints; robosuite builds a new controller
    object at every reset, so :meth:`torques` is given the current one."""

    def __init__(self, controller: Any, ctrl_range: np.ndarray) -> None:
        _check_supported(controller)
        self.model, self.data = controller.sim.model._model, controller.sim.data._data
        self.site = self.model.site(controller.ref_name).id
        self.qpos = slice(controller.qpos_index[0], controller.qpos_index[-1] + 1)
        self.qvel = slice(controller.qvel_index[0], controller.qvel_index[-1] + 1)
        self.low, self.high = ctrl_range[:, 0].copy(), ctrl_range[:, 1].copy()
        nv, n = self.model.nv, len(controller.qvel_index)
        self._jacp, self._jacr, self._mass = np.zeros((3, nv)), np.zeros((3, nv)), np.empty((nv, nv))
        # Same memory layouts as robosuite's arrays (C Jacobians, an F-ordered arm mass matrix): numba
        # compiles per layout and BLAS picks its kernels by it, which decides the rounding.
        self._j_full = np.zeros((6, n))
        self._j_pos, self._j_ori = self._j_full[:3], self._j_full[3:]
        self._wrench = np.zeros(6)

    def torques(self, c: Any) -> np.ndarray:
        """The arm's actuator commands for the current (``mj_step1``-updated) state and the goal of
        controller ``c``."""
        d, arm, j_full = self.data, self.qvel, self._j_full
        mujoco.mj_jacSite(self.model, d, self._jacp, self._jacr, self.site)
        j_full[:3], j_full[3:] = self._jacp[:, arm], self._jacr[:, arm]
        mujoco.mj_fullM(self.model, self._mass, d.qM)
        mass = np.asfortranarray(self._mass[arm, arm])
        # The base's velocity terms of robosuite's formula are exact zeros here (the base is welded to
        # the world, checked at construction), so "ref_vel - base_vel" is "ref_vel".
        force = (c.goal_pos - d.site_xpos[self.site]) * c.kp[0:3] + -np.dot(self._jacp, d.qvel) * c.kd[0:3]
        ori_error = orientation_error(c.goal_ori, np.array(d.site_xmat[self.site].reshape([3, 3])))
        torque = ori_error * c.kp[3:6] + -np.dot(self._jacr, d.qvel) * c.kd[3:6]
        _, lambda_pos, lambda_ori, nullspace = opspace_matrices(mass, j_full, self._j_pos, self._j_ori)
        np.dot(lambda_pos, force, out=self._wrench[:3])
        np.dot(lambda_ori, torque, out=self._wrench[3:])
        torques = np.dot(j_full.T, self._wrench) + d.qfrc_bias[arm]
        torques += nullspace_torques(mass, nullspace, c.initial_joint, d.qpos[self.qpos], d.qvel[arm])
        return np.minimum(np.maximum(torques, self.low), self.high)


def _check_supported(c: Any) -> None:
    """Refuse any controller setting the formula above does not implement."""
    m = c.sim.model._model
    base_body = m.site_bodyid[m.site(f"{c.naming_prefix}{c.part_name}_center").id]
    setting = {
        "type": type(c).__name__, "input_type": c.input_type, "input_ref_frame": c.input_ref_frame,
        "use_ori": c.use_ori, "impedance_mode": c.impedance_mode, "uncoupling": c.uncoupling,
        "interpolated": c.interpolator_pos is not None or c.interpolator_ori is not None,
        "base_welded": bool(m.body_weldid[base_body] == 0), "num_ref_sites": c.num_ref_sites,
        "contiguous_joints": _is_range(c.qpos_index) and _is_range(c.qvel_index),
    }
    supported = {
        "type": "OperationalSpaceController", "input_type": "absolute", "input_ref_frame": "world",
        "use_ori": False, "impedance_mode": "fixed", "uncoupling": True, "interpolated": False,
        "base_welded": True, "num_ref_sites": 1, "contiguous_joints": True,
    }
    if setting != supported:
        differing = {k: v for k, v in setting.items() if supported[k] != v}
        raise ValueError(f"OSCPositionTorques does not implement {differing}")


def _is_range(index: Any) -> bool:
    return list(index) == list(range(index[0], index[0] + len(index)))
