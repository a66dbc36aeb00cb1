"""2D Minecraft (chapter 5.3, modified from the crafting world of Andreas et al. 2017): gather raw
materials and craft tools along a technology tree up to a diamond.

A 16 x 16 room (walls included) holds six fixed 1-cell objects at random places: a ``workbench``
and a ``furnace`` (crafting stations) and four sources: a ``tree`` (wood), ``stone``, ``iron_ore``
and ``diamond``. The technology tree (each source needs the tool before it; amounts per craft):

==================  ==================  =========================
item                how                 needs
==================  ==================  =========================
wood                gather(tree)        -
stick               craft at workbench  1 wood
wood_pickaxe        craft at workbench  1 wood, 1 stick
stone               gather(stone)       wood_pickaxe
stone_pickaxe       craft at workbench  1 stone, 1 stick
iron_ore            gather(iron_ore)    stone_pickaxe
iron                craft at furnace    1 iron_ore, 1 wood (fuel)
iron_pickaxe        craft at workbench  1 iron, 1 stick
diamond             gather(diamond)     iron_pickaxe
==================  ==================  =========================

Factors (24): ``agent.x, agent.y, agent.dir``, ``x, y`` of the six objects, and the inventory
``inventory.<item>``: counts 0-5 of wood, stick, stone, iron_ore, iron; 0-1 for the three
pickaxes and the diamond. Actions (15): ``goTo`` each object, ``gather`` each source,
``craft`` each crafted item; a primitive applies to the object in front of the agent and does
nothing when its needs are unmet, when the product is at its cap, or for a tool already held.
Sources never run out; there are no obstacles (every layout is solvable). 300 steps.

``goal`` (default ``diamond``) is any item of the tree: success (reward 1, the episode ends) is
holding it; the stages are the tree's items up to it, in the order above, each reached once held.
Ground truth, stages and the rest of the contract as for the household tasks
(:mod:`envs.household`).

Measured (``python -m benchmarks.bench_household``): 0.7% positive off-diagonal labels under random
primitives; 22,000-24,000 steps/s per core; the scripted policy reaches the diamond on 50/50 unseen
seeds in 28 steps; random primitives never do in 300 steps (27% of the stages on average).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from envs.household.core import GridTaskEnv, Stage
from envs.household.grid import DX, DY, Layout, ObjectSpec, Placer, check_choice, check_room_size, faces
from envs.household.primitives import Action, go_to
from envs.household.rules import Rule
from envs.household.scripted import ScriptedPolicy

MAX_COUNT = 5


@dataclass(frozen=True)
class Recipe:
    """``product`` crafted at ``station`` from ``ingredients`` (name, amount)."""

    station: str
    ingredients: tuple[tuple[str, int], ...]


SOURCES = {"wood": ("tree", None), "stone": ("stone", "wood_pickaxe"), "iron_ore": ("iron_ore", "stone_pickaxe"),
           "diamond": ("diamond", "iron_pickaxe")}
"""Raw material -> (source object, tool needed)."""
RECIPES = {
    "stick": Recipe("workbench", (("wood", 1),)),
    "wood_pickaxe": Recipe("workbench", (("wood", 1), ("stick", 1))),
    "stone_pickaxe": Recipe("workbench", (("stone", 1), ("stick", 1))),
    "iron": Recipe("furnace", (("iron_ore", 1), ("wood", 1))),
    "iron_pickaxe": Recipe("workbench", (("iron", 1), ("stick", 1))),
}
ITEMS = ("wood", "stick", "wood_pickaxe", "stone", "stone_pickaxe", "iron_ore", "iron", "iron_pickaxe", "diamond")
"""The technology tree in stage order."""
CAPS = {item: 1 if item.endswith("pickaxe") or item == "diamond" else MAX_COUNT for item in ITEMS}
STAGE_NAMES = {"wood": "collect wood", "stick": "craft stick", "wood_pickaxe": "craft wooden pickaxe",
               "stone": "mine stone", "stone_pickaxe": "craft stone pickaxe", "iron_ore": "mine iron ore",
               "iron": "smelt iron", "iron_pickaxe": "craft iron pickaxe", "diamond": "mine diamond"}
OBJECTS = ("workbench", "furnace", "tree", "stone", "iron_ore", "diamond")
INVENTORY = ObjectSpec("inventory", located=False, states=tuple((item, CAPS[item] + 1) for item in ITEMS))
MIN_ROOM_SIZE = 6


class Minecraft2DEnv(GridTaskEnv):
    """2D Minecraft; see the module docstring for the tree, factors, actions and stages."""

    env_id = "minecraft2d"

    def __init__(self, *, goal: str = "diamond", room_size: int = 16, episode_length: int = 300,
                 render_mode: str | None = None) -> None:
        check_choice("goal", goal, ITEMS)
        check_room_size(room_size, MIN_ROOM_SIZE)
        self.goal = goal
        layout = Layout(int(room_size), (*(ObjectSpec(o) for o in OBJECTS), INVENTORY))
        actions = (*(go_to(layout, o) for o in OBJECTS),
                   *(_gather(layout, item) for item in SOURCES),
                   *(_craft(layout, item) for item in RECIPES))
        stages = tuple(Stage(STAGE_NAMES[item], lambda s, i=layout[f"inventory.{item}"]: s[i] > 0)
                       for item in ITEMS[: ITEMS.index(goal) + 1])
        super().__init__(layout, actions, (), stages, self._lay_out_room, episode_length, render_mode)

    def _lay_out_room(self, rng: np.random.Generator) -> list[int]:
        lay = self.layout
        state = [0] * lay.num_factors
        cells = Placer(lay.room_size, rng).distinct_cells(len(OBJECTS) + 1)
        for name, (x, y) in zip(("agent", *OBJECTS), cells):
            state[lay[f"{name}.x"]], state[lay[f"{name}.y"]] = x, y
        state[lay["agent.dir"]] = int(rng.integers(4))
        return state

    def config(self) -> dict[str, Any]:
        return {"goal": self.goal, "room_size": self.layout.room_size, "episode_length": self.episode_length}


def _in_front(lay: Layout, obj: str) -> tuple[int, ...]:
    """Indices of what decides whether ``obj`` is in front of the agent."""
    return tuple(lay[n] for n in ("agent.x", "agent.y", "agent.dir", f"{obj}.x", f"{obj}.y"))


def _gather(lay: Layout, item: str) -> Action:
    """``gather(source)``: one more ``item`` when the source is in front and the tool held."""
    source, tool = SOURCES[item]
    cap, child = CAPS[item], lay[f"inventory.{item}"]
    if tool is None:
        return Action("gather", source, (Rule(child, (child, *_in_front(lay, source)), lambda n, *front: (
            min(cap, n + 1) if faces(*front, 1, 1) else n)),))
    return Action("gather", source, (Rule(child, (child, *_in_front(lay, source), lay[f"inventory.{tool}"]),
                                          lambda n, x, y, d, ox, oy, has: min(cap, n + 1) if has and faces(
                                              x, y, d, ox, oy, 1, 1) else n),))


def _craft(lay: Layout, product: str) -> Action:
    """``craft(product)``: ingredients into one ``product`` at its station (in front), below its cap."""
    recipe = RECIPES[product]
    names = (product, *(name for name, _ in recipe.ingredients))
    needs = {product: 0, **dict(recipe.ingredients)}
    front = _in_front(lay, recipe.station)
    rules = []
    for k, child in enumerate(names):
        order = (child, *names[:k], *names[k + 1:])
        reads = (lay[f"inventory.{child}"], *front, *(lay[f"inventory.{n}"] for n in order[1:]))
        rules.append(Rule(reads[0], reads, _crafting(order, needs, CAPS[product], 1 if k == 0 else -needs[child])))
    return Action("craft", product, tuple(rules))


def _crafting(order: tuple[str, ...], needs: dict[str, int], cap: int, change: int) -> Callable[..., int]:
    """The rule of one inventory count under a craft: ``count + change`` when the craft happens
    (``order``: the counts the rule reads, the child's first)."""
    product = order.index(next(n for n in order if needs[n] == 0))
    wanted = tuple((order.index(n), k) for n, k in needs.items() if k)

    def count(n: int, x: int, y: int, d: int, ox: int, oy: int, *others: int) -> int:
        have = (n, *others)
        if have[product] >= cap or x + DX[d] != ox or y + DY[d] != oy:
            return n
        for i, k in wanted:
            if have[i] < k:
                return n
        return n + change

    return count


class Minecraft2DPolicy(ScriptedPolicy):
    """Obtains the goal by recursion on the tree: the first missing need of the goal, its first
    missing need, and so on, gathered or crafted (going to the source or station first)."""

    def __init__(self, env: Minecraft2DEnv) -> None:
        super().__init__(env)
        self.goal = env.goal

    def choose(self, s: dict[str, int]) -> int:
        if s[f"inventory.{self.goal}"]:
            return self.wait("workbench")
        return self.obtain(s, self.goal)

    def obtain(self, s: dict[str, int], item: str) -> int:
        """The next action toward one more ``item``."""
        if item in SOURCES:
            source, tool = SOURCES[item]
            if tool is not None and not s[f"inventory.{tool}"]:
                return self.obtain(s, tool)
            return self.apply(s, "gather", source)
        recipe = RECIPES[item]
        for name, amount in recipe.ingredients:
            if s[f"inventory.{name}"] < amount:
                return self.obtain(s, name)
        return self.apply(s, "craft", item, at=recipe.station)
