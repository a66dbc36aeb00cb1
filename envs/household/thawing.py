"""Thawing (chapters 5.3 and 6.3, Mini-BEHAVIOR's thawing frozen food): take food out of the fridge
and thaw it in the sink.

Objects: the agent; a fridge (2 x 2, ``open``); a sink (2 x 2, ``on``); fish, olive and date (items,
each with ``frozen`` 0-5). Factors (21): ``agent.x, agent.y, agent.dir``, ``fridge.x, fridge.y,
fridge.open``, ``sink.x, sink.y, sink.on``, then ``x, y, held, frozen`` of fish, olive and date.
Actions (14): ``goTo`` each object, ``pick`` and ``place`` each food, ``toggle(sink)``,
``open(fridge)``, ``close(fridge)``. Room 10 x 10 (walls included), 300 steps.

The food starts in the closed fridge, frozen (5). Object states update before the action: a food
lying in the fridge (not held, on a fridge cell) gets ``frozen + 1``, one lying in a sink that is
on ``frozen - 1`` (clipped to 0-5). A food in a closed fridge can be neither picked nor placed.

Tasks (``task``): ``thaw-fish``, ``thaw-olive``, ``thaw-date`` (chapter 6's three), success when
that food's ``frozen`` is 0; ``thaw-all`` (Mini-BEHAVIOR's original, all three thawed).
Stages: open fridge, pick <food>, <food> in sink, turn on sink, thaw <food> (for every food of the
task; the last stage of ``thaw-all`` is all three thawed).

Measured (``python -m benchmarks.bench_household``, table in :mod:`envs.household`): 1.8% positive
off-diagonal labels under random primitives (chapter 5: at most 3%); 22,000-30,000 steps/s per
core; the scripted policy succeeds on 50/50 unseen seeds (12 steps for one food, 20 for all).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from envs.household.core import GridTaskEnv, Stage
from envs.household.grid import Layout, ObjectSpec, Placer, check_choice, check_room_size, inside
from envs.household.primitives import go_to, pick, place, set_open, toggle
from envs.household.rules import Rule

FROZEN_MAX = 5
FOODS = ("fish", "olive", "date")
FRIDGE = ObjectSpec("fridge", width=2, height=2, states=(("open", 2),))
SINK = ObjectSpec("sink", width=2, height=2, states=(("on", 2),))
TASKS = ("thaw-fish", "thaw-olive", "thaw-date", "thaw-all")
MIN_ROOM_SIZE = 7
"""The smallest room where the sink fits wherever the fridge is."""


class ThawingEnv(GridTaskEnv):
    """Thawing; see the module docstring for factors, actions, rules, tasks and stages."""

    env_id = "thawing"

    def __init__(self, *, task: str = "thaw-fish", room_size: int = 10, episode_length: int = 300,
                 render_mode: str | None = None, action_mode: str = "primitives") -> None:
        check_choice("task", task, TASKS)
        check_room_size(room_size, MIN_ROOM_SIZE)
        self.task = task
        self.targets = FOODS if task == "thaw-all" else (task.removeprefix("thaw-"),)
        foods = tuple(ObjectSpec(f, movable=True, states=(("frozen", FROZEN_MAX + 1),)) for f in FOODS)
        layout = Layout(int(room_size), (FRIDGE, SINK, *foods))
        actions = (
            *(go_to(layout, o) for o in ("fridge", "sink", *FOODS)),
            *(pick(layout, f, containers=("fridge",)) for f in FOODS),
            *(place(layout, f, containers=("fridge",)) for f in FOODS),
            toggle(layout, "sink"), set_open(layout, "fridge", 1), set_open(layout, "fridge", 0),
        )
        updates = tuple(_thaw(layout, f) for f in FOODS)
        super().__init__(layout, actions, updates, _stages(layout, self.targets), self._lay_out_room,
                         episode_length, render_mode, action_mode)

    def _lay_out_room(self, rng: np.random.Generator) -> list[int]:
        lay = self.layout
        placer = Placer(lay.room_size, rng)
        state = [0] * lay.num_factors
        fx, fy = placer.furniture(FRIDGE.width, FRIDGE.height)
        state[lay["fridge.x"]], state[lay["fridge.y"]] = fx, fy
        state[lay["sink.x"]], state[lay["sink.y"]] = placer.furniture(SINK.width, SINK.height)
        shelves = [(fx + i, fy + j) for i in range(FRIDGE.width) for j in range(FRIDGE.height)]
        for food, k in zip(FOODS, rng.permutation(len(shelves))):
            state[lay[f"{food}.x"]], state[lay[f"{food}.y"]] = shelves[k]
            state[lay[f"{food}.frozen"]] = FROZEN_MAX
        state[lay["agent.x"]], state[lay["agent.y"]] = placer.free_cell()
        state[lay["agent.dir"]] = int(rng.integers(4))
        return state

    def config(self) -> dict[str, Any]:
        return {"task": self.task, "room_size": self.layout.room_size, "episode_length": self.episode_length,
                **self._mode_config()}


def _thaw(lay: Layout, food: str) -> Rule:
    """``frozen`` +1 in the fridge, -1 in a running sink, from the state at ``t``."""
    fw, fh, sw, sh = FRIDGE.width, FRIDGE.height, SINK.width, SINK.height

    def frozen(level: int, x: int, y: int, held: int, fx: int, fy: int, sx: int, sy: int, on: int) -> int:
        if held:
            return level
        change = int(inside(x, y, fx, fy, fw, fh)) - int(on and inside(x, y, sx, sy, sw, sh))
        return min(FROZEN_MAX, max(0, level + change))

    reads = tuple(lay[n] for n in (f"{food}.frozen", f"{food}.x", f"{food}.y", f"{food}.held",
                                   "fridge.x", "fridge.y", "sink.x", "sink.y", "sink.on"))
    return Rule(reads[0], reads, frozen)


def _in_sink(lay: Layout, food: str) -> Stage:
    x, y, held = lay[f"{food}.x"], lay[f"{food}.y"], lay[f"{food}.held"]
    sx, sy = lay["sink.x"], lay["sink.y"]
    return Stage(f"{food} in sink", lambda s: not s[held] and inside(s[x], s[y], s[sx], s[sy], SINK.width, SINK.height))


def _stages(lay: Layout, targets: tuple[str, ...]) -> tuple[Stage, ...]:
    fridge_open, sink_on = lay["fridge.open"], lay["sink.on"]
    held = {f: lay[f"{f}.held"] for f in targets}
    frozen = {f: lay[f"{f}.frozen"] for f in targets}
    stages = [Stage("open fridge", lambda s: s[fridge_open] == 1),
              *(Stage(f"pick {f}", lambda s, i=held[f]: s[i] == 1) for f in targets),
              *(_in_sink(lay, f) for f in targets),
              Stage("turn on sink", lambda s: s[sink_on] == 1),
              *(Stage(f"thaw {f}", lambda s, i=frozen[f]: s[i] == 0) for f in targets)]
    if len(targets) > 1:
        stages.append(Stage("thaw all", lambda s: all(s[i] == 0 for i in frozen.values())))
    return tuple(stages)
