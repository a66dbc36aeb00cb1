"""Installing Printer (chapter 6.3, Mini-BEHAVIOR): pick up the printer, put it on the table, turn it on.

Objects: the agent; a table (3 x 2 cells, ``clean``); a printer (an item: ``on``, ``on_table``,
``ready``). Factors (12): ``agent.x, agent.y, agent.dir, table.x, table.y, table.clean,
printer.x, printer.y, printer.held, printer.on, printer.on_table, printer.ready``.
Actions (5): ``goTo(table), goTo(printer), pick(printer), place(printer), toggle(printer)``.
Room 8 x 8 (walls included), 150 steps.

Object states update before the action: ``printer.on_table <- the printer lies on the table``
(not held, on a table cell) and ``printer.ready <- on and on_table and table.clean``, both from the
state at ``t``. The table is always clean (``table.clean`` is a constant factor: the notes' rule
reads it, nothing here dirties it). Success (reward 1, episode ends): ``printer.ready``.

Stages: pick printer, printer on table, turn on printer, install printer.

Measured (``python -m benchmarks.bench_household``, table in :mod:`envs.household`): 4.9% positive
off-diagonal labels under random primitives (12 factors: denser than the larger tasks);
50,000-53,000 steps/s per core; the scripted policy succeeds on 50/50 unseen seeds in 6 steps, the
random one in 99% of episodes.
"""
from __future__ import annotations

import numpy as np

from envs.household.core import GridTaskEnv, Stage
from envs.household.grid import Layout, ObjectSpec, Placer, check_room_size, inside
from envs.household.primitives import go_to, pick, place, toggle
from envs.household.rules import Rule

TABLE = ObjectSpec("table", width=3, height=2, states=(("clean", 2),))
PRINTER = ObjectSpec("printer", movable=True, states=(("on", 2), ("on_table", 2), ("ready", 2)))
MIN_ROOM_SIZE = 6


class InstallingPrinterEnv(GridTaskEnv):
    """Installing Printer; see the module docstring for factors, actions, rules and stages."""

    env_id = "installing-printer"

    def __init__(self, *, room_size: int = 8, episode_length: int = 150, render_mode: str | None = None,
                 action_mode: str = "primitives") -> None:
        check_room_size(room_size, MIN_ROOM_SIZE)
        layout = Layout(int(room_size), (TABLE, PRINTER))
        actions = (go_to(layout, "table"), go_to(layout, "printer"), pick(layout, "printer"),
                   place(layout, "printer"), toggle(layout, "printer"))
        super().__init__(layout, actions, _updates(layout), _stages(layout), self._lay_out_room,
                         episode_length, render_mode, action_mode)

    def constant_factors(self) -> tuple[str, ...]:
        return ("table.clean",)

    def _lay_out_room(self, rng: np.random.Generator) -> list[int]:
        lay = self.layout
        placer = Placer(lay.room_size, rng)
        state = [0] * lay.num_factors
        state[lay["table.x"]], state[lay["table.y"]] = placer.furniture(TABLE.width, TABLE.height)
        (px, py), (ax, ay) = placer.distinct_cells(2)
        state[lay["printer.x"]], state[lay["printer.y"]] = px, py
        state[lay["agent.x"]], state[lay["agent.y"]] = ax, ay
        state[lay["agent.dir"]] = int(rng.integers(4))
        state[lay["table.clean"]] = 1
        return state


def _updates(lay: Layout) -> tuple[Rule, ...]:
    w, h = TABLE.width, TABLE.height
    on_table = Rule(lay["printer.on_table"], (lay["printer.on_table"], lay["printer.x"], lay["printer.y"],
                                              lay["printer.held"], lay["table.x"], lay["table.y"]),
                    lambda old, px, py, held, tx, ty: int(not held and inside(px, py, tx, ty, w, h)))
    ready = Rule(lay["printer.ready"], (lay["printer.ready"], lay["printer.on"], lay["printer.on_table"],
                                        lay["table.clean"]),
                 lambda old, on, on_table, clean: int(on and on_table and clean))
    return on_table, ready


def _stages(lay: Layout) -> tuple[Stage, ...]:
    held, on_table, on, ready = (lay[f"printer.{a}"] for a in ("held", "on_table", "on", "ready"))
    return (Stage("pick printer", lambda s: s[held] == 1),
            Stage("printer on table", lambda s: s[on_table] == 1),
            Stage("turn on printer", lambda s: s[on] == 1),
            Stage("install printer", lambda s: s[ready] == 1))
