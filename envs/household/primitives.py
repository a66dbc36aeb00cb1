"""Action primitives on objects (chapter 5: ``goTo(obj)``, ``pick(obj)``, ...) as rules.

Each primitive is one action of a Discrete space, applied to one object; when its precondition
fails it changes nothing. The agent acts on the cell in front of it:

- ``goTo(o)``: the agent moves next to ``o`` and faces it (:func:`envs.household.grid.approach`);
  an item in the agent's hands cannot be gone to.
- ``pick(o)``: an item in front of the agent is taken into its hands (it can hold several, as in
  Mini-BEHAVIOR); an item inside a closed container (the fridge) cannot be reached.
- ``place(o)``: a held item is put on the cell in front (floor or furniture); not into a closed
  container, not into a wall.
- ``toggle(o)``: switches ``o.on`` when ``o`` is in front (an item in hand cannot be switched).
- ``open(o)`` / ``close(o)``: sets ``o.open`` when ``o`` is in front.

An item's ``x, y`` are where it lies; while held (``held = 1``) they keep the cell it was picked
from, and ``place`` gives it a new one. So moving the agent writes only the agent's factors.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from envs.household.grid import DX, DY, Layout, approach, faces, inside
from envs.household.rules import Rule


@dataclass(frozen=True)
class Action:
    """One Discrete action: ``primitive(target)`` and the rules it applies."""

    primitive: str
    target: str
    rules: tuple[Rule, ...]

    @property
    def name(self) -> str:
        return f"{self.primitive}({self.target})"


def _agent(layout: Layout) -> tuple[int, int, int]:
    return layout["agent.x"], layout["agent.y"], layout["agent.dir"]


def go_to(layout: Layout, target: str) -> Action:
    """``goTo(target)``: the agent to the approach cell of ``target``, facing it."""
    spec, r = layout.objects[target], layout.room_size
    ax, ay, ad = _agent(layout)
    tx, ty = layout[f"{target}.x"], layout[f"{target}.y"]
    h = spec.height
    if not spec.movable:
        return Action("goTo", target, (
            Rule(ax, (ax, tx), lambda x, to: to),
            Rule(ay, (ay, ty), lambda y, to: approach(to, h, r)[0]),
            Rule(ad, (ad, ty), lambda d, to: approach(to, h, r)[1]),
        ))
    th = layout[f"{target}.held"]
    return Action("goTo", target, (
        Rule(ax, (ax, tx, th), lambda x, to, held: x if held else to),
        Rule(ay, (ay, ty, th), lambda y, to, held: y if held else approach(to, h, r)[0]),
        Rule(ad, (ad, ty, th), lambda d, to, held: d if held else approach(to, h, r)[1]),
    ))


def _containers(layout: Layout, containers: Sequence[str]) -> tuple[tuple[int, ...], tuple[tuple[int, int], ...]]:
    """The ``x, y, open`` indices of openable containers, flat, and their footprints."""
    reads = tuple(layout[f"{c}.{a}"] for c in containers for a in ("x", "y", "open"))
    sizes = tuple((layout.objects[c].width, layout.objects[c].height) for c in containers)
    return reads, sizes


def _reachable(px: int, py: int, boxes: Sequence[int], sizes: Sequence[tuple[int, int]]) -> bool:
    """Whether cell ``(px, py)`` is outside every closed container (``boxes``: x, y, open each)."""
    for k, (w, h) in enumerate(sizes):
        x, y, is_open = boxes[3 * k: 3 * k + 3]
        if not is_open and inside(px, py, x, y, w, h):
            return False
    return True


def pick(layout: Layout, item: str, containers: Sequence[str] = ()) -> Action:
    """``pick(item)``: into the agent's hands if in front and not shut in a container."""
    ax, ay, ad = _agent(layout)
    held, ix, iy = layout[f"{item}.held"], layout[f"{item}.x"], layout[f"{item}.y"]
    boxes, sizes = _containers(layout, containers)

    def picked(h: int, x: int, y: int, d: int, px: int, py: int, *cs: int) -> int:
        if h:
            return 1
        return int(x + DX[d] == px and y + DY[d] == py and _reachable(px, py, cs, sizes))

    return Action("pick", item, (Rule(held, (held, ax, ay, ad, ix, iy, *boxes), picked),))


def place(layout: Layout, item: str, containers: Sequence[str] = ()) -> Action:
    """``place(item)``: a held item onto the cell in front, unless it is a wall or a shut container."""
    ax, ay, ad = _agent(layout)
    held, ix, iy = layout[f"{item}.held"], layout[f"{item}.x"], layout[f"{item}.y"]
    boxes, sizes = _containers(layout, containers)
    last = layout.room_size - 2

    def can(h: int, x: int, y: int, d: int, cs: Sequence[int]) -> bool:
        fx, fy = x + DX[d], y + DY[d]
        return bool(h) and 1 <= fx <= last and 1 <= fy <= last and _reachable(fx, fy, cs, sizes)

    def new_x(old: int, h: int, x: int, y: int, d: int, *cs: int) -> int:
        return x + DX[d] if can(h, x, y, d, cs) else old

    def new_y(old: int, h: int, x: int, y: int, d: int, *cs: int) -> int:
        return y + DY[d] if can(h, x, y, d, cs) else old

    def new_held(h: int, x: int, y: int, d: int, *cs: int) -> int:
        return 0 if can(h, x, y, d, cs) else h

    agent = (ax, ay, ad, *boxes)
    return Action("place", item, (
        Rule(ix, (ix, held, *agent), new_x),
        Rule(iy, (iy, held, *agent), new_y),
        Rule(held, (held, *agent), new_held),
    ))


def toggle(layout: Layout, obj: str) -> Action:
    """``toggle(obj)``: flips ``obj.on`` when ``obj`` is in front (and not in the agent's hands)."""
    spec = layout.objects[obj]
    w, h = spec.width, spec.height
    on, ox, oy = layout[f"{obj}.on"], layout[f"{obj}.x"], layout[f"{obj}.y"]
    ax, ay, ad = _agent(layout)
    if not spec.movable:
        return Action("toggle", obj, (Rule(on, (on, ax, ay, ad, ox, oy), lambda v, x, y, d, px, py: (
            1 - v if faces(x, y, d, px, py, w, h) else v)),))
    held = layout[f"{obj}.held"]
    return Action("toggle", obj, (Rule(on, (on, ax, ay, ad, ox, oy, held), lambda v, x, y, d, px, py, hd: (
        1 - v if not hd and faces(x, y, d, px, py, w, h) else v)),))


def set_open(layout: Layout, obj: str, value: int) -> Action:
    """``open(obj)`` (``value`` 1) or ``close(obj)`` (0) when ``obj`` is in front."""
    spec = layout.objects[obj]
    w, h = spec.width, spec.height
    state, ox, oy = layout[f"{obj}.open"], layout[f"{obj}.x"], layout[f"{obj}.y"]
    ax, ay, ad = _agent(layout)
    return Action("open" if value else "close", obj, (Rule(state, (state, ax, ay, ad, ox, oy), lambda v, x, y, d, px, py: (
        value if faces(x, y, d, px, py, w, h) else v)),))


ACTION_MODES = ("primitives", "grid")
"""How the agent acts: ``primitives`` (the default: ``goTo(o)`` teleports next to ``o``) or ``grid``
(Mini-BEHAVIOR's own actions: turn left, turn right, move forward one cell, and the object actions
on the cell in front), see :func:`grid_actions`."""


def turn(layout: Layout, step: int) -> Action:
    """``left`` (``step`` -1, counter-clockwise as MiniGrid) or ``right`` (+1): the agent turns in place."""
    ad = layout["agent.dir"]
    return Action("left" if step < 0 else "right", "agent", (Rule(ad, (ad,), lambda d: (d + step) % 4),))


def forward(layout: Layout) -> Action:
    """``forward``: the agent moves one cell the way it faces, unless that cell is wall or a cell of a
    piece of furniture (a located object that is not an item). Items do not block (they lie on the
    floor and the agent may stand on them, as on MiniGrid's overlappable objects)."""
    ax, ay, ad = _agent(layout)
    furniture = [o for o, spec in layout.objects.items() if o != "agent" and spec.located and not spec.movable]
    corners = tuple(layout[f"{o}.{a}"] for o in furniture for a in ("x", "y"))
    sizes = tuple((layout.objects[o].width, layout.objects[o].height) for o in furniture)
    last = layout.room_size - 2

    def target(x: int, y: int, d: int, cs: Sequence[int]) -> tuple[int, int]:
        fx, fy = x + DX[d], y + DY[d]
        if not (1 <= fx <= last and 1 <= fy <= last):
            return x, y
        if any(inside(fx, fy, cs[2 * k], cs[2 * k + 1], w, h) for k, (w, h) in enumerate(sizes)):
            return x, y
        return fx, fy

    return Action("forward", "agent", (
        Rule(ax, (ax, ay, ad, *corners), lambda x, y, d, *cs: target(x, y, d, cs)[0]),
        Rule(ay, (ay, ax, ad, *corners), lambda y, x, d, *cs: target(x, y, d, cs)[1]),
    ))


def grid_actions(layout: Layout, actions: Sequence[Action], mode: str) -> tuple[Action, ...]:
    """The actions of ``mode``: ``primitives`` leaves ``actions`` as they are; ``grid`` replaces every
    ``goTo`` by ``left``, ``right`` and ``forward`` (first, in that order) and keeps the object
    actions (``pick``, ``place``, ``toggle``, ``open``, ``close``), which already act only on the
    object in the cell the agent faces.

    Deviation from Mini-BEHAVIOR: its ``pickup``/``drop``/``toggle`` take whatever object is in front
    (one action per object slot of the cell); here each object action still names its object
    (``pick(printer)``), so the action set stays the env's own and the object's factors keep their
    edges as in primitive mode. While no two items share the cell in front the two coincide up to
    the labelling of the actions.
    """
    if mode not in ACTION_MODES:
        raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {mode!r}")
    if mode == "primitives":
        return tuple(actions)
    return (turn(layout, -1), turn(layout, 1), forward(layout),
            *(a for a in actions if a.primitive != "goTo"))
