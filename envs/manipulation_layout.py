"""Shared constants of the manipulation environment: factor layout, scene geometry, contact groups.

Pure data (no simulator import), so the ground truth (:mod:`envs.manipulation_truth`) and the
scripted skills (:mod:`envs.skills`) can be used without loading robosuite.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

OBJECTS = ("eef", "grp", "mov", "unm", "rand", "mk1", "mk2", "mk3")
OBJECT_DIMS = {"eef": ("x", "y", "z"), "grp": ("0", "1")} | {o: ("x", "y", "z") for o in OBJECTS[2:]}
FACTOR_NAMES = tuple(f"{o}.{d}" for o in OBJECTS for d in OBJECT_DIMS[o])
"""``eef.x .. eef.z``, ``grp.0``, ``grp.1``, then ``x, y, z`` of every cube and marker: 23 factors."""
FACTOR_OBJECTS = tuple(o for o in OBJECTS for _ in OBJECT_DIMS[o])
NUM_FACTORS = len(FACTOR_NAMES)
MARKERS = OBJECTS[5:]


def factor_slice(obj: str) -> slice:
    """The factor (observation) indices of object ``obj``."""
    start = FACTOR_OBJECTS.index(obj)
    return slice(start, start + len(OBJECT_DIMS[obj]))


EEF, GRP, MOV, UNM, RAND = (factor_slice(o) for o in OBJECTS[:5])

CONSTANT_FACTORS = ("unm.z", "rand.z", "mk1.z", "mk2.z", "mk3.z")
"""Factors with the same value in every step of every episode (short of an intervention), by
construction: ``unm`` and ``rand`` sit on the table and the markers lie on it (kinematic bodies whose
walks are horizontal). The true edges they cause (``unm.z`` and ``rand.z`` block the robot and
``mov``) cannot show in the scene's data; :func:`causal.graph_metrics.score_graph` leaves their
columns out of its identifiable scores. (``unm.x``/``unm.y`` are constant within an episode but
drawn anew at each reset, so they vary.)"""

TABLE_TOP = np.array([0.0, 0.0, 0.8])
"""World position of the centre of the table's top surface (metres)."""
TABLE_SIZE = (0.8, 0.8, 0.05)
MOV_HALF, FIXED_HALF, MARKER_RADIUS = 0.02, 0.025, 0.015
"""Half-sizes of ``mov`` and of ``unm``/``rand``; the markers' radius."""
REGION_LOW, REGION_HIGH = np.array([-0.15, -0.2]), np.array([0.15, 0.2])
"""Table area (x, y) where cubes and markers start and where ``rand`` and the markers walk."""
WORKSPACE_LOW, WORKSPACE_HIGH = np.array([-0.25, -0.3, 0.805]), np.array([0.2, 0.3, 1.0])
"""Box the end-effector's goal is clipped to (at its floor the fingertips touch the table)."""

ROBOT, MOV_BODY, UNM_BODY, RAND_BODY, STATIC = range(5)
CONTACT_GROUPS = ("robot", "mov", "unm", "rand", "static")
"""Rows/columns of a step's contact matrix: the robot's moving links, the three cubes, the rest."""


@dataclass(frozen=True)
class SceneLayout:
    """Which cubes and markers a table scene holds, and the factor layout and contact groups that follow.

    ``movable``: free-jointed cubes the robot can move (half-size :data:`MOV_HALF`); ``kinematic``:
    mocap cubes nothing can move (half-size :data:`FIXED_HALF`), of which those in ``still`` never move
    and the others walk; ``markers``: walking visual-only discs. Factors: ``eef.x/y/z``, ``grp.0/1``,
    then ``x/y/z`` of every movable cube, kinematic cube and marker, in that order. Contact groups:
    the robot, every cube, the static rest."""

    movable: tuple[str, ...]
    kinematic: tuple[str, ...]
    markers: tuple[str, ...]
    still: tuple[str, ...] = ("unm",)
    oriented: tuple[str, ...] = ()
    """Movable bodies whose yaw (radians about the vertical, in (-pi, pi]) is a factor after ``x, y, z``:
    the L-shaped tool, whose reach depends on how it is turned."""
    shapes: tuple[tuple[str, str], ...] = ()
    """``(body, shape)`` for bodies that are not plain cubes: ``"l-tool"`` (:data:`TOOL_HANDLE_HALF`,
    :data:`TOOL_HOOK_HALF`) or ``"open-box"`` (:data:`BOX_INNER_HALF`, :data:`BOX_WALL`)."""
    velocities: tuple[str, ...] = ()
    """Bodies whose velocities are factors too (:meth:`with_velocities`: the arm's end-effector, the
    fingers and every movable body), after all the positions: ``eef.vx/vy/vz`` (m/s), the
    end-effector's orientation ``eef.rx/ry/rz`` (rad) and angular velocity ``eef.wx/wy/wz`` (rad/s),
    ``grp.v0/v1``, ``<cube>.vx/vy/vz`` and, for an oriented body, ``.vyaw`` (rad/s). Without them the
    robosuite scenes are not Markov in their factors (docs/environments.md, "Velocity factors");
    positions keep their indices either way."""

    def with_velocities(self) -> "SceneLayout":
        """This layout with velocity factors for ``eef``, ``grp`` and every movable body."""
        return replace(self, velocities=("eef", "grp") + self.movable)

    def shape(self, obj: str) -> str:
        """``"cube"``, ``"l-tool"`` or ``"open-box"``."""
        return dict(self.shapes).get(obj, "cube")

    @property
    def objects(self) -> tuple[str, ...]:
        return ("eef", "grp") + self.movable + self.kinematic + self.markers

    @property
    def mocap(self) -> tuple[str, ...]:
        """The kinematic bodies in the simulator's order: kinematic cubes, then markers."""
        return self.kinematic + self.markers

    def dims(self, obj: str) -> tuple[str, ...]:
        """The position dimensions of ``obj`` (coordinates, the tool's yaw, the fingers' joints)."""
        if obj == "grp":
            return OBJECT_DIMS["grp"]
        return ("x", "y", "z", "yaw") if obj in self.oriented else ("x", "y", "z")

    def velocity_dims(self, obj: str) -> tuple[str, ...]:
        """The velocity dimensions of ``obj`` (none unless it is in :attr:`velocities`); the end-effector
        has its orientation (``rx, ry, rz``: a rotation vector from its orientation at reset) and
        angular velocity (``wx, wy, wz``) after its linear velocity: its controller holds the
        orientation only approximately, and without them the arm is not Markov."""
        if obj not in self.velocities:
            return ()
        if obj == "eef":
            return ("vx", "vy", "vz", "rx", "ry", "rz", "wx", "wy", "wz")
        return tuple(f"v{d}" for d in self.dims(obj))

    @cached_property
    def _factors(self) -> tuple[tuple[str, str], ...]:
        """``(object, dimension)`` of every factor, positions first (computed once: the truth reads
        the layout at every step)."""
        positions = tuple((o, d) for o in self.objects for d in self.dims(o))
        return positions + tuple((o, d) for o in self.objects for d in self.velocity_dims(o))

    @property
    def factor_names(self) -> tuple[str, ...]:
        return tuple(f"{o}.{d}" for o, d in self._factors)

    @property
    def factor_objects(self) -> tuple[str, ...]:
        return tuple(o for o, _ in self._factors)

    @property
    def num_factors(self) -> int:
        return len(self._factors)

    def factor_slice(self, obj: str) -> slice:
        """The factor (observation) indices of object ``obj``'s position dimensions (:meth:`dims`)."""
        start = self.factor_objects.index(obj)
        return slice(start, start + len(self.dims(obj)))

    def factor_indices(self, obj: str) -> np.ndarray:
        """All of ``obj``'s factor indices: its positions, then its velocities (if any)."""
        return np.array([k for k, o in enumerate(self.factor_objects) if o == obj], dtype=np.int64)

    @property
    def contact_groups(self) -> tuple[str, ...]:
        """Rows/columns of a step's contact matrix: ``robot``, every cube, ``static`` (last)."""
        return ("robot",) + self.movable + self.kinematic + ("static",)

    @property
    def constant_factors(self) -> tuple[str, ...]:
        """The z of every kinematic cube and marker (they sit on the table and walk horizontally)."""
        return tuple(f"{o}.z" for o in self.mocap)


MANIPULATION = SceneLayout(movable=("mov",), kinematic=("unm", "rand"), markers=MARKERS)
"""Chapter 3's scene (the module constants above are its layout)."""
BLOCK = SceneLayout(movable=("mov1", "mov2", "mov3"), kinematic=("unm",), markers=())
"""Chapter 4's block scene (Fig. 4.7 left): three movable cubes and one fixed to the table."""
assert MANIPULATION.factor_names == FACTOR_NAMES and MANIPULATION.constant_factors == CONSTANT_FACTORS
assert MANIPULATION.contact_groups == CONTACT_GROUPS

TOOL_HANDLE_HALF = (0.13, 0.012, 0.012)
"""Half-sizes (m) of the L-shaped tool's handle, along the tool's own x axis."""
TOOL_HOOK_HALF = (0.012, 0.055, 0.012)
"""Half-sizes (m) of the tool's hook, across the far end of the handle towards the tool's -y."""
TOOL_HOOK_CENTRE = (TOOL_HANDLE_HALF[0] - TOOL_HOOK_HALF[0], -(TOOL_HOOK_HALF[1] - TOOL_HANDLE_HALF[1]))
"""The hook's centre in the tool's frame (the handle's centre is the tool's origin)."""
TOOL_GRIP = (-0.08, 0.0)
"""Where on the handle (tool frame) the scripted skills and the Series reward grasp the tool."""
BOX_INNER_HALF, BOX_WALL, BOX_HEIGHT = 0.05, 0.005, 0.03
"""The open box of the tool-use scene: inner half-width, wall half-thickness, wall half-height (m)."""
TOOL_USE = SceneLayout(movable=("tool", "block"), kinematic=("box",), markers=(), still=("box",),
                       oriented=("tool",), shapes=(("tool", "l-tool"), ("box", "open-box")))
"""Chapter 4's tool-use scene (Fig. 4.7 left, bottom): an L-shaped tool, a cube out of the arm's
reach, and an open box fixed on the table. 15 factors: ``eef``, ``grp``, ``tool.x/y/z/yaw``,
``block.x/y/z``, ``box.x/y/z``."""
