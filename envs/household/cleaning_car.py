"""Cleaning Car (chapter 6.3; chapter 5.3 calls it CarWash, Mini-BEHAVIOR's cleaning a car):
soak a rag in the sink, clean the car with it, clean the rag with soap in the bucket.

Objects: the agent; a car (3 x 2, ``stained``); a sink (2 x 2, ``on``); a bucket (1 x 1,
``soaped``); soap (an item); a rag (an item: ``soak`` 0-5, ``dirty`` 0-5). Factors (20):
``agent.x, agent.y, agent.dir``, ``car.x, car.y, car.stained``, ``sink.x, sink.y, sink.on``,
``bucket.x, bucket.y, bucket.soaped``, ``soap.x, soap.y, soap.held``, ``rag.x, rag.y, rag.held,
rag.soak, rag.dirty``. Actions (10): ``goTo`` each object, ``pick`` and ``place`` soap and rag,
``toggle(sink)``. Room 10 x 10 (walls included); 100 steps by default (chapter 5's CarWash), 300
for chapter 6 (``episode_length``).

At reset the car is stained, the sink off, the bucket without soap, the rag dry and clean. Object
states update before the action, from the state at ``t`` ("lying in" = not held, on a cell of):

- a rag lying in a sink that is on soaks: ``soak + 1`` (at most 5; 5 is soaked);
- a soaked rag lying on a stained car cleans it (``stained`` 0) and takes the dirt (``dirty`` 5);
- soap lying in the bucket soaps it (``soaped`` 1, for good);
- a rag lying in a soaped bucket is cleaned: ``dirty - 1`` (at least 0).

Tasks (``task``), each a prerequisite of the next: ``soak-rag`` (``rag.soak`` 5), ``clean-car``
(``car.stained`` 0), ``clean-rag`` (car clean and ``rag.dirty`` 0). Stages: pick rag, turn on sink,
soak rag, then clean car, then soap in bucket, clean rag (as far as the task goes).

Measured (``python -m benchmarks.bench_household``, table in :mod:`envs.household`): 1.9-2.0%
positive off-diagonal labels under random primitives (chapter 5: at most 3%); 26,000-40,000
steps/s per core; the scripted policy succeeds on 50/50 unseen seeds in 28 steps (``clean-rag``),
random primitives in 0% of 100-step and 14% of 300-step episodes.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from envs.household.core import GridTaskEnv, Stage
from envs.household.grid import Layout, ObjectSpec, Placer, check_choice, check_room_size, inside
from envs.household.primitives import go_to, pick, place, toggle
from envs.household.rules import Rule

LEVEL_MAX = 5
CAR = ObjectSpec("car", width=3, height=2, states=(("stained", 2),))
SINK = ObjectSpec("sink", width=2, height=2, states=(("on", 2),))
BUCKET = ObjectSpec("bucket", states=(("soaped", 2),))
SOAP = ObjectSpec("soap", movable=True)
RAG = ObjectSpec("rag", movable=True, states=(("soak", LEVEL_MAX + 1), ("dirty", LEVEL_MAX + 1)))
TASKS = ("soak-rag", "clean-car", "clean-rag")
STAGES_PER_TASK = {"soak-rag": 3, "clean-car": 4, "clean-rag": 6}
MIN_ROOM_SIZE = 7
"""The smallest room where the sink and the bucket fit wherever the car is."""


class CleaningCarEnv(GridTaskEnv):
    """Cleaning Car; see the module docstring for factors, actions, rules, tasks and stages."""

    env_id = "cleaning-car"

    def __init__(self, *, task: str = "clean-rag", room_size: int = 10, episode_length: int = 100,
                 render_mode: str | None = None, action_mode: str = "primitives") -> None:
        check_choice("task", task, TASKS)
        check_room_size(room_size, MIN_ROOM_SIZE)
        self.task = task
        layout = Layout(int(room_size), (CAR, SINK, BUCKET, SOAP, RAG))
        actions = (
            *(go_to(layout, o) for o in ("car", "sink", "bucket", "soap", "rag")),
            pick(layout, "soap"), pick(layout, "rag"), place(layout, "soap"), place(layout, "rag"),
            toggle(layout, "sink"),
        )
        stages = _stages(layout)[: STAGES_PER_TASK[task]]
        super().__init__(layout, actions, _updates(layout), stages, self._lay_out_room, episode_length, render_mode,
                         action_mode)

    def _lay_out_room(self, rng: np.random.Generator) -> list[int]:
        lay = self.layout
        placer = Placer(lay.room_size, rng)
        state = [0] * lay.num_factors
        for spec in (CAR, SINK, BUCKET):
            state[lay[f"{spec.name}.x"]], state[lay[f"{spec.name}.y"]] = placer.furniture(spec.width, spec.height)
        for name, (x, y) in zip(("soap", "rag", "agent"), placer.distinct_cells(3)):
            state[lay[f"{name}.x"]], state[lay[f"{name}.y"]] = x, y
        state[lay["agent.dir"]] = int(rng.integers(4))
        state[lay["car.stained"]] = 1
        return state

    def config(self) -> dict[str, Any]:
        return {"task": self.task, "room_size": self.layout.room_size, "episode_length": self.episode_length,
                **self._mode_config()}


def _lying_in(x: int, y: int, held: int, spec: ObjectSpec, ox: int, oy: int) -> bool:
    return not held and inside(x, y, ox, oy, spec.width, spec.height)


def _soak(level: int, x: int, y: int, held: int, sx: int, sy: int, on: int) -> int:
    return min(LEVEL_MAX, level + 1) if on and _lying_in(x, y, held, SINK, sx, sy) else level


def _cleans_car(x: int, y: int, held: int, soak: int, cx: int, cy: int, stained: int) -> bool:
    return bool(stained) and soak == LEVEL_MAX and _lying_in(x, y, held, CAR, cx, cy)


def _stained(stained: int, x: int, y: int, held: int, soak: int, cx: int, cy: int) -> int:
    return 0 if _cleans_car(x, y, held, soak, cx, cy, stained) else stained


def _dirty(level: int, x: int, y: int, held: int, soak: int, cx: int, cy: int, stained: int,
           bx: int, by: int, soaped: int) -> int:
    if _cleans_car(x, y, held, soak, cx, cy, stained):
        return LEVEL_MAX
    if soaped and _lying_in(x, y, held, BUCKET, bx, by):
        return max(0, level - 1)
    return level


def _soaped(soaped: int, x: int, y: int, held: int, bx: int, by: int) -> int:
    return 1 if _lying_in(x, y, held, BUCKET, bx, by) else soaped


def _updates(lay: Layout) -> tuple[Rule, ...]:
    def rule(*names: str, fn: Any) -> Rule:
        reads = tuple(lay[n] for n in names)
        return Rule(reads[0], reads, fn)

    rag = ("rag.x", "rag.y", "rag.held")
    return (
        rule("rag.soak", *rag, "sink.x", "sink.y", "sink.on", fn=_soak),
        rule("car.stained", *rag, "rag.soak", "car.x", "car.y", fn=_stained),
        rule("rag.dirty", *rag, "rag.soak", "car.x", "car.y", "car.stained", "bucket.x", "bucket.y",
             "bucket.soaped", fn=_dirty),
        rule("bucket.soaped", "soap.x", "soap.y", "soap.held", "bucket.x", "bucket.y", fn=_soaped),
    )


def _stages(lay: Layout) -> tuple[Stage, ...]:
    """All six stages of ``clean-rag``; ``soak-rag`` ends after the third, ``clean-car`` the fourth."""
    held, on, soak, stained = lay["rag.held"], lay["sink.on"], lay["rag.soak"], lay["car.stained"]
    soaped, dirty = lay["bucket.soaped"], lay["rag.dirty"]
    return (Stage("pick rag", lambda s: s[held] == 1),
            Stage("turn on sink", lambda s: s[on] == 1),
            Stage("soak rag", lambda s: s[soak] == LEVEL_MAX),
            Stage("clean car", lambda s: s[stained] == 0),
            Stage("soap in bucket", lambda s: s[soaped] == 1),
            Stage("clean rag", lambda s: s[stained] == 0 and s[dirty] == 0))
