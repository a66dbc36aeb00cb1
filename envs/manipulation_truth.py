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
"""
from __future__ import annotations

import numpy as np

from envs.manipulation_layout import (
    EEF, GRP, MOV, MOV_BODY, NUM_FACTORS, RAND, RAND_BODY, ROBOT, STATIC, UNM, UNM_BODY,
)

ACTION = NUM_FACTORS
"""Column of the action in a graph."""
_ROBOT_ROWS = np.r_[EEF, GRP]
_GROUP_FACTORS = {ROBOT: _ROBOT_ROWS, MOV_BODY: np.r_[MOV], UNM_BODY: np.r_[UNM], RAND_BODY: np.r_[RAND]}


def _no_contact_graph() -> np.ndarray:
    graph = np.eye(NUM_FACTORS, NUM_FACTORS + 1, dtype=np.uint8)
    for block in (EEF, GRP, MOV):
        graph[block, block] = 1
    graph[_ROBOT_ROWS, ACTION] = 1
    return graph


def local_graph(contacts: np.ndarray) -> np.ndarray:
    """The graph of one step from its symmetric boolean ``[5, 5]`` contact matrix (groups robot,
    mov, unm, rand, static: :data:`envs.manipulation_layout.CONTACT_GROUPS`)."""
    touch = np.asarray(contacts, dtype=bool) & ~np.eye(len(contacts), dtype=bool)
    graph = _no_contact_graph()
    if touch[ROBOT].any():
        graph[np.ix_(_ROBOT_ROWS, _ROBOT_ROWS)] = 1
    held = bool(touch[ROBOT, MOV_BODY])
    for group in ([ROBOT, MOV_BODY],) if held else ([ROBOT], [MOV_BODY]):
        rows = np.concatenate([_GROUP_FACTORS[body] for body in group])
        for kinematic in (UNM_BODY, RAND_BODY):
            if touch[group, kinematic].any():
                graph[np.ix_(rows, _GROUP_FACTORS[kinematic])] = 1
    if held:
        graph[np.ix_(_GROUP_FACTORS[MOV_BODY], _ROBOT_ROWS)] = 1
        graph[np.ix_(_ROBOT_ROWS, _GROUP_FACTORS[MOV_BODY])] = 1
        graph[_GROUP_FACTORS[MOV_BODY], ACTION] = 1
    return graph


def global_graph() -> np.ndarray:
    """The one-step ground truth: the union of the local graphs, i.e. everything touching."""
    everything = np.ones((STATIC + 1, STATIC + 1), dtype=bool)
    return local_graph(everything)
