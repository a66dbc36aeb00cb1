"""Chemical Match with chapter 4's distractors: the cheap environment for CBM's tests and quick runs.

Chemical Match (colours, positions, goal colours; reward = fraction of objects at their goal colour
after the step) with ``controllable`` distractors (random projections of the one-hot action) and
``uncontrollable`` ones (U(-1, 1) every step) appended to the observation (:mod:`envs.distractors`).
Its truths: the Match graph with the distractors' rows and columns (:meth:`Distractors.extend_graph`),
and the reward's parents at t: the parents of every colour and goal colour at t+1
(:func:`envs.task_truth.parents_through_step`) through the dependencies the dynamics *have*, which
differ from the graph's in one place: every factor keeps a self-edge there by Assumption 4, but a
colour that every action overwrites (the action sets it or re-samples it: on the ``full`` graph the
last object's) does not depend on its old value, so it is no parent of the reward. The reward's
parents are the other colours, the goal colours and the action; the true minimal task abstraction
(Theorem 4.1) keeps those colours and the goals and drops the positions and all distractors, while
CDL's task-independent abstraction keeps every colour and the controllable distractors (descendants of
the action) and drops the goals.

Task ``match-first`` rewards matching object 0 only (the fraction is over that one object): its reward
reads ``obj0.color`` and ``obj0.goal_color``, so on the ``full`` graph (where object 0 is a root) the
minimal abstraction is those two factors, while every colour stays controllable: the situation of
Fig. 4.5, where CDL keeps the movable blocks a task does not need and CBM drops them.
"""
from __future__ import annotations

import dataclasses
import json
from typing import Any

import gymnasium as gym
import numpy as np

from envs.chemical_match import ChemicalMatchEnv
from envs.distractors import Distractors, parse_distractors
from envs.task_truth import parents_through_step
from proto.messages import EnvSpec

TASKS = ("match", "match-first")
"""``match``: every object at its goal colour (Chemical Match's reward); ``match-first``: object 0 only."""


class ChemicalDistractorsEnv(ChemicalMatchEnv):
    """Observation ``[4N + C + U]``: Chemical Match's ``[4N]``, then ``cd.0 .. cd.{C-1}`` and
    ``ud.0 .. ud.{U-1}``. ``distractors`` is ``"C,U"`` (default 20 of each); ``distractor_seed``
    fixes the projection; ``task`` is one of :data:`TASKS`; ``distractor_ood = (lo, hi)`` lifts every
    distractor value out of its training range [-1, 1] into [-hi, -lo] u [lo, hi] (out-of-distribution
    evaluation, :class:`envs.distractors.Distractors`). Every :class:`ChemicalMatchEnv` option passes
    through (``ood_noise_scale`` too: positions drawn at that scale)."""

    def __init__(self, *, distractors: str = "20,20", distractor_seed: int = 0, task: str = "match",
                 distractor_ood: tuple[float, float] | None = None, **kwargs: Any) -> None:
        if task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {task!r}")
        self.num_controllable, self.num_uncontrollable = parse_distractors(distractors)
        self.distractor_seed, self.task = distractor_seed, task
        self.distractor_ood = None if distractor_ood is None else (float(distractor_ood[0]), float(distractor_ood[1]))
        super().__init__(**kwargs)
        self.task_objects = tuple(range(self.num_objects)) if task == "match" else (0,)
        self.distractors = Distractors(self.num_controllable, self.num_uncontrollable, "categorical",
                                       int(self.action_space.n), distractor_seed, self.distractor_ood)
        self._match_width = 4 * self.num_objects
        self._global_graph = self.distractors.extend_graph(self._global_graph)
        self._global_graph.flags.writeable = False
        self._local_graphs = tuple(self.distractors.extend_graph(g) for g in self._local_graphs)
        self._values = np.zeros(self.distractors.count)

    @property
    def factor_names(self) -> tuple[str, ...]:
        """Chemical Match's factors, then ``cd.k`` and ``ud.k``."""
        extra = tuple(f"cd.{k}" for k in range(self.num_controllable)) + \
            tuple(f"ud.{k}" for k in range(self.num_uncontrollable))
        return super().factor_names + extra

    @property
    def reward_parents(self) -> np.ndarray:
        """uint8 ``[d + 1]``: the true parents at t of the task's reward: of the colours and goal colours
        it reads at t+1 (Match: every colour, every goal, the action)."""
        n = self.num_objects
        read = [3 * k for k in self.task_objects] + [3 * n + k for k in self.task_objects]
        return parents_through_step(self.dependencies(), read)

    def dependencies(self) -> np.ndarray:
        """The one-step graph without the self-edges the dynamics do not have (positions and distractors
        are drawn anew, a colour that every action sets or re-samples forgets its old value)."""
        graph = self._global_graph.copy()
        n, size = self.num_objects, graph.shape[0]
        kept = [3 * n + k for k in range(n)]  # goal colours are constant
        kept += [3 * j for j in range(n) if any(i != j and j not in self.dag.descendants(i) for i in range(n))]
        forgets = np.setdiff1d(np.arange(size), kept)
        graph[forgets, forgets] = 0
        return graph

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Chemical Match's reset, controllable distractors at 0, uncontrollable ones drawn."""
        _, info = super().reset(seed=seed, options=options)
        self._values = self.distractors.reset(self.np_random)
        return self._observation(), info

    def step(self, action: int | np.integer) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """The distractors' new values, then Chemical Match's step (its reward ignores them)."""
        self._decode(action)
        self._values = self.distractors.step(int(action), self.np_random)
        return super().step(action)

    def match_fraction(self, obs: np.ndarray) -> np.floating | np.ndarray:
        """The task's reward: the fraction of its objects at their goal colour, from the first ``4N``
        columns of ``obs``."""
        obs, n = np.asarray(obs), self.num_objects
        objects = list(self.task_objects)
        return np.mean(obs[..., 0 : 3 * n : 3][..., objects] == obs[..., 3 * n : 4 * n][..., objects], axis=-1)

    def sample_next_states(self, states: np.ndarray, action: int) -> np.ndarray:
        """Chemical Match's batched simulator, with the distractors' new values appended."""
        states = np.asarray(states)
        nxt = super().sample_next_states(states[:, : self._match_width], action)
        values = np.stack([self.distractors.step(action, self.np_random) for _ in range(len(states))])
        return np.concatenate([nxt, values.astype(np.float32)], axis=1)

    def set_state(self, obs: np.ndarray) -> None:
        """Put the environment (goals and distractors included) in the state of observation ``obs``."""
        obs = np.asarray(obs, dtype=np.float64)
        if obs.shape != (self._match_width + self.distractors.count,):
            raise ValueError(f"observations have shape ({self._match_width + self.distractors.count},), "
                             f"got {obs.shape}")
        super().set_state(obs[: self._match_width])
        self._values = obs[self._match_width :].copy()

    def env_spec(self) -> EnvSpec:
        """Chemical Match's spec with the distractors (continuous, scale 1) and the true reward parents."""
        spec = super().env_spec()
        m = self.distractors.count
        return dataclasses.replace(
            spec, env_id="chemical-distractors", factor_names=self.factor_names,
            factor_kinds=spec.factor_kinds + ("continuous",) * m, factor_sizes=spec.factor_sizes + (1,) * m,
            factor_objects=spec.factor_objects + self.distractors.objects,
            factor_locs=spec.factor_locs + (0.0,) * m, factor_scales=spec.factor_scales + (1.0,) * m,
            global_graph=self._global_graph.copy(), reward_parents=self.reward_parents,
            config_json=json.dumps(self.config()),
        )

    def config(self) -> dict[str, Any]:
        """Chemical Match's configuration plus the distractor counts and seed."""
        return {**super().config(), "distractors": f"{self.num_controllable},{self.num_uncontrollable}",
                "distractor_seed": self.distractor_seed, "task": self.task,
                **({"distractor_ood": list(self.distractor_ood)} if self.distractor_ood else {})}

    def _make_observation_space(self) -> gym.spaces.Box:
        match = super()._make_observation_space()
        m = self.num_controllable + self.num_uncontrollable
        bound = 1.0 if self.distractor_ood is None else self.distractor_ood[1]
        return gym.spaces.Box(np.concatenate([match.low, -bound * np.ones(m, np.float32)]),
                              np.concatenate([match.high, bound * np.ones(m, np.float32)]), dtype=np.float32)

    def _observation(self) -> np.ndarray:
        return np.concatenate([super()._observation(), self._values.astype(np.float32)])
