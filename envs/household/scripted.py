"""Policies for the grid tasks: scripted ones that complete each task, and random primitives.

A policy has ``reset()`` and ``act(observation) -> np.ndarray`` (the action index as a 1-element
float32 array), like :class:`services.env_worker.core.RandomPolicy`. Scripted policies read only
the observation: each step they pick the first unmet sub-goal and either apply its primitive, if
the object is in front of the agent, or go to that object. Rooms have no obstacles, so every
layout is solvable and these succeed in every episode (measured by ``benchmarks.bench_household``).
"""
from __future__ import annotations

from abc import ABC, abstractmethod

import gymnasium as gym
import numpy as np

from envs.household.cleaning_car import LEVEL_MAX, CleaningCarEnv
from envs.household.core import GridTaskEnv
from envs.household.grid import faces, inside
from envs.household.printer import InstallingPrinterEnv
from envs.household.thawing import ThawingEnv


class RandomPrimitivePolicy:
    """Uniformly random primitives on objects (the exploration baseline of chapters 5-6)."""

    version = 0
    over_skills = False

    def __init__(self, action_space: gym.spaces.Discrete, seed: int) -> None:
        self.num_actions = int(action_space.n)
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        """Nothing to forget between episodes."""

    def act(self, observation: np.ndarray) -> np.ndarray:
        return np.array([self.rng.integers(self.num_actions)], dtype=np.float32)


class ScriptedPolicy(ABC):
    """Base of the scripted policies: reads factors by name, goes to objects and applies primitives."""

    version = 0
    over_skills = False

    def __init__(self, env: GridTaskEnv) -> None:
        self.env = env
        self.layout = env.layout
        self._actions = {name: a for a, name in enumerate(env.action_names)}

    def reset(self) -> None:
        """Scripted policies keep no memory between steps."""

    def act(self, observation: np.ndarray) -> np.ndarray:
        state = dict(zip(self.layout.names, observation.astype(int).tolist()))
        return np.array([self.choose(state)], dtype=np.float32)

    @abstractmethod
    def choose(self, s: dict[str, int]) -> int:
        """The action for state ``s`` (factor name -> value)."""

    def facing(self, s: dict[str, int], obj: str) -> bool:
        spec = self.layout.objects[obj]
        return faces(s["agent.x"], s["agent.y"], s["agent.dir"], s[f"{obj}.x"], s[f"{obj}.y"], spec.width, spec.height)

    def lies_in(self, s: dict[str, int], item: str, furniture: str) -> bool:
        spec = self.layout.objects[furniture]
        return not s[f"{item}.held"] and inside(s[f"{item}.x"], s[f"{item}.y"], s[f"{furniture}.x"],
                                                   s[f"{furniture}.y"], spec.width, spec.height)

    def apply(self, s: dict[str, int], primitive: str, obj: str, at: str | None = None) -> int:
        """``primitive(obj)`` if ``at`` (default ``obj``) is in front of the agent, else ``goTo(at)``."""
        at = at or obj
        if self.facing(s, at):
            return self._actions[f"{primitive}({obj})"]
        return self._actions[f"goTo({at})"]

    def wait(self, obj: str) -> int:
        """An action that changes nothing but the agent's place: ``goTo(obj)`` of furniture."""
        return self._actions[f"goTo({obj})"]


class InstallingPrinterPolicy(ScriptedPolicy):
    """Pick up the printer, put it on the table, turn it on, wait for it to be ready."""

    def choose(self, s: dict[str, int]) -> int:
        if s["printer.held"]:
            return self.apply(s, "place", "printer", at="table")
        if not self.lies_in(s, "printer", "table"):
            return self.apply(s, "pick", "printer")
        if not s["printer.on"]:
            return self.apply(s, "toggle", "printer")
        return self.wait("table")


class ThawingPolicy(ScriptedPolicy):
    """Open the fridge, carry every food of the task to the sink, turn it on, wait."""

    def __init__(self, env: ThawingEnv) -> None:
        super().__init__(env)
        self.targets = env.targets

    def choose(self, s: dict[str, int]) -> int:
        for food in self.targets:
            if s[f"{food}.held"]:
                return self.apply(s, "place", food, at="sink")
            if self.lies_in(s, food, "sink") or not s[f"{food}.frozen"]:
                continue
            if self.lies_in(s, food, "fridge") and not s["fridge.open"]:
                return self.apply(s, "open", "fridge")
            return self.apply(s, "pick", food)
        if not s["sink.on"]:
            return self.apply(s, "toggle", "sink")
        return self.wait("sink")


class CleaningCarPolicy(ScriptedPolicy):
    """Soak the rag in the running sink, lay it on the car, soap the bucket, clean the rag in it."""

    def __init__(self, env: CleaningCarEnv) -> None:
        super().__init__(env)
        self.task = env.task

    def choose(self, s: dict[str, int]) -> int:
        if s["rag.soak"] < LEVEL_MAX:
            if not s["sink.on"] and self.lies_in(s, "rag", "sink"):
                return self.apply(s, "toggle", "sink")
            return self.bring(s, "rag", "sink")
        if s["car.stained"]:
            return self.bring(s, "rag", "car")
        if not s["bucket.soaped"]:
            return self.bring(s, "soap", "bucket")
        return self.bring(s, "rag", "bucket")

    def bring(self, s: dict[str, int], item: str, to: str) -> int:
        """Carry ``item`` to ``to`` and leave it there (wait while it lies there)."""
        if s[f"{item}.held"]:
            return self.apply(s, "place", item, at=to)
        if self.lies_in(s, item, to):
            return self.wait(to)
        return self.apply(s, "pick", item)


def scripted_policy(env: gym.Env) -> ScriptedPolicy:
    """The scripted policy of a household task (wrapped or not); 2D Minecraft's is
    :class:`envs.minecraft2d.Minecraft2DPolicy`."""
    env = env.unwrapped
    for env_type, policy in ((InstallingPrinterEnv, InstallingPrinterPolicy), (ThawingEnv, ThawingPolicy),
                             (CleaningCarEnv, CleaningCarPolicy)):
        if isinstance(env, env_type):
            return policy(env)
    raise TypeError(f"no scripted household policy for {type(env).__name__}")
