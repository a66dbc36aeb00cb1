"""Factor layout and ground-truth graphs of the manipulation environment (dissertation 3.3.1).

Every factor is one dimension (23 in all, the chapter's count): ``eef.x/y/z`` (end-effector
position), ``grp.0/1`` (the two fingers' slide joints), then ``x/y/z`` of ``mov``, ``unm``,
``rand``, ``mk1``, ``mk2``, ``mk3``. A graph is a uint8 ``[23, 24]`` matrix, row = factor at t+1,
column = factor at t, the 4-D action in the last column.

An edge ``i -> j`` means that *intervening* on dimension ``i`` at time t (anywhere in the scene's
state space) can change the distribution of ``j`` at t+1, given the action. What the dynamics do:

* **Self-edges.** ``eef``, ``grp`` and ``mov`` are full blocks: the operational-space controller's
  tracking of one axis depends on the arm's whole configuration (all of ``eef``), the two fingers
  are pushed against each other through anything they squeeze, and a cube's motion on any axis
  depends on all of its coordinates (resting on the table vs held in the air, at the table's edge).
  ``unm`` never moves and ``rand`` and the markers follow per-axis clipped random walks (their z is
  constant), so those are diagonal only.
* **Action.** The action sets the arm's next goal and the fingers' target: ``eef`` and ``grp``
  depend on it. ``mov`` does too: the policy step lasts 0.1 s, and a held or pushed cube moves
  *within* it by the displacement the action commands, which ``s_t`` alone does not determine.
* **Contact.** Within one policy step, force travels only through bodies that can move: the robot
  and ``mov``. ``unm`` and ``rand`` are kinematic (mocap) bodies, so they act on whatever touches
  them and nothing acts on them. Whether two bodies touch, and along which axis one blocks the
  other, depends on all three coordinates of both, so every contact edge is a full block:

  - robot touches anything (table or cube): ``eef <- grp`` and ``grp <- eef`` (the fingers are the
    part of the arm that touches: an open gripper straddles a cube that a closed one lands on, and
    the arm's position decides where the fingers close);
  - robot touches ``mov``: the robot (``eef``, ``grp``) and ``mov`` depend on each other, and
    ``mov`` on the action;
  - a robot-``mov`` group touches ``unm`` or ``rand``: every member of the group depends on it
    (``unm`` under a held cube blocks the arm too).

* **Markers** have no collision geometry: they read only themselves, and nothing reads them.

The global graph is the union of the local graphs over all contact patterns (everything touching).
Dimensions that are constant in the scene's own episodes (``unm.z``, ``rand.z``, the markers' z)
keep the edges an intervention on them would reveal (``unm.z`` raised to the arm's height blocks
it), so ``unm`` and ``rand`` are action-relevant in every dimension, as the chapter says. The
scene's own data carry no information about a constant, so a learner cannot find those edges:
the identifiable scores leave out the columns of
:data:`envs.manipulation_layout.CONSTANT_FACTORS` (``unm.z``, ``rand.z``, ``mk*.z``).

Resulting classes (:func:`causal.abstraction.cdl_abstraction`): controllable ``eef``, ``grp``,
``mov``; action-relevant ``unm``, ``rand``; action-irrelevant ``mk1``-``mk3``.

**Velocity factors** (``velocities=True``: :meth:`envs.manipulation_layout.SceneLayout.with_velocities`)
belong to their body: ``eef.vx/vy/vz``, ``eef.rx/ry/rz`` (orientation) and ``eef.wx/wy/wz`` to ``eef``, ``grp.v0/v1`` to ``grp``, a cube's velocities to
the cube. Every rule above then applies to a body's positions and velocities together (the rows
and columns of a body are all its factors): a body's next position and velocity depend on its
current ones, contact couples the velocities as it couples the positions, and the action drives
the robot's (and a held cube's) velocities.

**Several movable cubes** (chapter 4's block scene, :data:`envs.manipulation_layout.BLOCK`): force
travels through every chain of touching movable bodies, so the rule above applies to each connected
group of the robot and the movable cubes in contact during the step: every member depends on every
other (full blocks), every member on the kinematic cubes any member touches, and every cube in the
robot's group on the action. With one movable cube this is exactly the rule above.
"""
from __future__ import annotations

import numpy as np

from envs.manipulation_layout import MANIPULATION, NUM_FACTORS, SceneLayout

ACTION = NUM_FACTORS
"""Column of the action in a manipulation-scene graph (``layout.num_factors`` in general)."""


def _rows(layout: SceneLayout, body: str) -> np.ndarray:
    objects = ("eef", "grp") if body == "robot" else (body,)
    return np.concatenate([layout.factor_indices(o) for o in objects])


def _no_contact_graph(layout: SceneLayout) -> np.ndarray:
    n = layout.num_factors
    graph = np.eye(n, n + 1, dtype=np.uint8)
    for obj in ("eef", "grp", *layout.movable):
        block = layout.factor_indices(obj)
        graph[np.ix_(block, block)] = 1
    graph[_rows(layout, "robot"), n] = 1
    return graph


def _touching_groups(touch: np.ndarray, dynamic: list[int]) -> list[list[int]]:
    """Connected components of the contact graph among the ``dynamic`` groups (robot, movable cubes)."""
    groups, seen = [], set()
    for first in dynamic:
        if first in seen:
            continue
        component, frontier = [first], [first]
        seen.add(first)
        while frontier:
            body = frontier.pop()
            for other in dynamic:
                if other not in seen and touch[body, other]:
                    seen.add(other)
                    component.append(other)
                    frontier.append(other)
        groups.append(sorted(component))
    return groups


def local_graph(contacts: np.ndarray, layout: SceneLayout = MANIPULATION) -> np.ndarray:
    """The graph of one step from its symmetric boolean contact matrix over ``layout.contact_groups``
    (robot, the cubes, static: :data:`envs.manipulation_layout.CONTACT_GROUPS` in chapter 3's scene)."""
    touch = np.asarray(contacts, dtype=bool) & ~np.eye(len(contacts), dtype=bool)
    names, n = layout.contact_groups, layout.num_factors
    graph = _no_contact_graph(layout)
    robot_rows = _rows(layout, "robot")
    if touch[0].any():
        graph[np.ix_(robot_rows, robot_rows)] = 1
    dynamic = list(range(1 + len(layout.movable)))
    kinematic = range(len(dynamic), len(dynamic) + len(layout.kinematic))
    for group in _touching_groups(touch, dynamic):
        rows = np.concatenate([_rows(layout, names[b]) for b in group])
        for k in kinematic:
            if touch[group, k].any():
                graph[np.ix_(rows, _rows(layout, names[k]))] = 1
        for a in group:
            for b in group:
                if a != b:
                    graph[np.ix_(_rows(layout, names[a]), _rows(layout, names[b]))] = 1
        if 0 in group:
            graph[rows, n] = 1
    return graph


def global_graph(layout: SceneLayout = MANIPULATION) -> np.ndarray:
    """The one-step ground truth: the union of the local graphs, i.e. everything touching."""
    everything = np.ones((len(layout.contact_groups),) * 2, dtype=bool)
    return local_graph(everything, layout)
