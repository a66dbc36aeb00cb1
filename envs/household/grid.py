"""Rooms, objects and the factor layout shared by the household tasks and 2D Minecraft.

A room is ``room_size`` x ``room_size`` cells whose border is wall (MiniGrid's convention, which
Mini-BEHAVIOR inherits): the floor is ``x, y`` in ``[1, room_size - 2]``, ``x`` grows east and ``y``
south. Furniture spans ``width`` x ``height`` cells from its north-west corner ``(x, y)`` and never
moves; an item (``movable``) lies on one cell, on the floor or on a piece of furniture, and may
share it with other items (Mini-BEHAVIOR stacks objects in a cell).

The state is one categorical factor per object attribute, in the order the objects are given
(the agent first): ``x``, ``y`` for every located object, ``held`` for items, then the object's own
states (``open``, ``on``, ``frozen``, ...). Every factor's values are the integers
``[low, high]``: a furniture corner only where the piece fits inside the walls, so every point of
the observation box is a valid state (the truth tests intervene anywhere in it).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EAST, SOUTH, WEST, NORTH = 0, 1, 2, 3
"""Agent directions (MiniGrid's: 0 right, 1 down, 2 left, 3 up)."""
DX = (1, 0, -1, 0)
DY = (0, 1, 0, -1)
MAX_ROOM_SIZE = 32
"""Largest room accepted (factor sizes grow with it)."""


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a task: its footprint, whether it can be carried, and its own states.

    ``states`` pairs each state's name with its number of values (``("frozen", 6)``: levels 0-5).
    ``located`` is False for an object without a place in the room (2D Minecraft's inventory).
    """

    name: str
    width: int = 1
    height: int = 1
    movable: bool = False
    states: tuple[tuple[str, int], ...] = ()
    located: bool = True


AGENT = ObjectSpec("agent", states=(("dir", 4),))


@dataclass(frozen=True)
class Factor:
    """One categorical factor: ``object.attribute`` with values in ``[low, high]``."""

    name: str
    obj: str
    low: int
    high: int


class Layout:
    """The factors of a room with ``objects`` (the agent is added first), and their indices."""

    def __init__(self, room_size: int, objects: tuple[ObjectSpec, ...]) -> None:
        self.room_size = room_size
        self.objects = {spec.name: spec for spec in (AGENT, *objects)}
        self.factors = tuple(f for spec in self.objects.values() for f in _factors(spec, room_size))
        self._index = {f.name: i for i, f in enumerate(self.factors)}

    def __getitem__(self, name: str) -> int:
        """Index of factor ``name`` (``"fish.frozen"``)."""
        return self._index[name]

    @property
    def num_factors(self) -> int:
        return len(self.factors)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.factors)

    @property
    def low(self) -> np.ndarray:
        return np.array([f.low for f in self.factors], dtype=np.float32)

    @property
    def high(self) -> np.ndarray:
        return np.array([f.high for f in self.factors], dtype=np.float32)

    @property
    def sizes(self) -> tuple[int, ...]:
        """Categories per factor: values are category indices ``0 .. high``."""
        return tuple(f.high + 1 for f in self.factors)

    def domain(self, index: int) -> range:
        """The values factor ``index`` can take."""
        f = self.factors[index]
        return range(f.low, f.high + 1)

    def check_state(self, state: np.ndarray) -> list[int]:
        """``state`` as a list of ints; ValueError unless it is a valid point of the layout."""
        values = np.asarray(state, dtype=np.float64).reshape(-1)
        if values.shape != (self.num_factors,):
            raise ValueError(f"state must have {self.num_factors} factors, got shape {np.shape(state)}")
        ints = values.astype(np.int64)
        bad = [f"{f.name}={v} not in [{f.low}, {f.high}]" for f, v, i in zip(self.factors, values, ints)
               if v != i or not f.low <= i <= f.high]
        if bad:
            raise ValueError("invalid state: " + ", ".join(bad))
        return ints.tolist()


def _factors(spec: ObjectSpec, room_size: int) -> list[Factor]:
    out = []
    if spec.located:
        out.append(Factor(f"{spec.name}.x", spec.name, 1, room_size - 1 - spec.width))
        out.append(Factor(f"{spec.name}.y", spec.name, 1, room_size - 1 - spec.height))
    if spec.movable:
        out.append(Factor(f"{spec.name}.held", spec.name, 0, 1))
    out.extend(Factor(f"{spec.name}.{state}", spec.name, 0, n - 1) for state, n in spec.states)
    return out


def check_room_size(room_size: int, minimum: int) -> None:
    """ValueError unless ``room_size`` is an int in ``[minimum, MAX_ROOM_SIZE]``."""
    if isinstance(room_size, bool) or not isinstance(room_size, (int, np.integer)) or not (
        minimum <= room_size <= MAX_ROOM_SIZE
    ):
        raise ValueError(f"room_size must be an integer in [{minimum}, {MAX_ROOM_SIZE}] "
                         f"(walls included), got {room_size!r}")


def check_choice(name: str, value: object, valid: tuple[str, ...]) -> None:
    """ValueError naming the valid values unless ``value`` is one of them."""
    if value not in valid:
        raise ValueError(f"{name} must be one of {valid}, got {value!r}")


def check_episode_length(episode_length: int) -> None:
    if isinstance(episode_length, bool) or not isinstance(episode_length, (int, np.integer)) or episode_length < 1:
        raise ValueError(f"episode_length must be an integer >= 1, got {episode_length!r}")


def inside(px: int, py: int, x: int, y: int, width: int, height: int) -> bool:
    """Whether cell ``(px, py)`` lies in the footprint with corner ``(x, y)``."""
    return x <= px < x + width and y <= py < y + height


def faces(ax: int, ay: int, d: int, x: int, y: int, width: int, height: int) -> bool:
    """Whether the cell in front of an agent at ``(ax, ay)`` facing ``d`` is in the footprint."""
    return x <= ax + DX[d] < x + width and y <= ay + DY[d] < y + height


def approach(y: int, height: int, room_size: int) -> tuple[int, int]:
    """Where ``goTo`` puts the agent relative to a footprint at row ``y``: ``(row, direction)``.

    The cell below the footprint's west column, facing north; on the bottom row, the cell above it,
    facing south. The column is the footprint's own ``x``, so ``goTo`` reads only the target's
    corner and nothing else in the room (the agent does not collide with objects: it moves by
    primitives, not by walking).
    """
    if y + height <= room_size - 2:
        return y + height, NORTH
    return y - 1, SOUTH


class Placer:
    """Draws non-overlapping footprints and free cells at reset, from a numpy generator."""

    def __init__(self, room_size: int, rng: np.random.Generator) -> None:
        self.room_size, self.rng = room_size, rng
        self.covered: set[tuple[int, int]] = set()

    def furniture(self, width: int, height: int) -> tuple[int, int]:
        """A corner whose footprint covers no cell taken so far (the footprint is then taken): a
        few random draws, then a uniform choice among every corner that fits."""
        r = self.room_size
        for _ in range(100):
            corner = int(self.rng.integers(1, r - width)), int(self.rng.integers(1, r - height))
            if self._take(corner, width, height):
                return corner
        fits = [(x, y) for x in range(1, r - width) for y in range(1, r - height)
                if not self._cells((x, y), width, height) & self.covered]
        if not fits:
            raise RuntimeError(f"no room for a {width}x{height} piece in a {r}x{r} room")
        corner = fits[int(self.rng.integers(len(fits)))]
        self._take(corner, width, height)
        return corner

    @staticmethod
    def _cells(corner: tuple[int, int], width: int, height: int) -> set[tuple[int, int]]:
        return {(corner[0] + i, corner[1] + j) for i in range(width) for j in range(height)}

    def _take(self, corner: tuple[int, int], width: int, height: int) -> bool:
        cells = self._cells(corner, width, height)
        if cells & self.covered:
            return False
        self.covered |= cells
        return True

    def free_cell(self) -> tuple[int, int]:
        """A floor cell outside every footprint taken (not taken itself: items may share cells)."""
        free = [(x, y) for x in range(1, self.room_size - 1) for y in range(1, self.room_size - 1)
                if (x, y) not in self.covered]
        x, y = free[int(self.rng.integers(len(free)))]
        return x, y

    def distinct_cells(self, n: int) -> list[tuple[int, int]]:
        """``n`` different free cells, each then taken (so nothing placed later lands on them)."""
        cells = []
        for _ in range(n):
            cell = self.free_cell()
            self.covered.add(cell)
            cells.append(cell)
        return cells
