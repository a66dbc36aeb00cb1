"""The environment registry: everything the services need to know about an environment, by name.

One :class:`EnvEntry` per environment: how to build it (and which run options its constructor
takes), what ground truth it has (a global graph, local graphs per step, none), which factors are
constant by construction, its tasks, its skill options and default collection policy, and which
post-run evaluation applies. Services look entries up; they never compare environment names.

Every entry is also registered with Gymnasium (``gymnasium.make("causeway/Chemical-v0")``), with the
same keyword arguments as :func:`make_env`.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field, fields
from typing import Any, Callable, Mapping

import gymnasium as gym

from envs import manipulation_layout
from proto.settings import doc

TRUTH_KINDS = ("global", "local", "global+local", "none")


@dataclass(frozen=True)
class EnvOptions:
    """Environment construction options a run can set; each environment takes the ones it lists."""

    graph: str = doc("full", "Chemical object graph: collider, chain, full or a path to a DAG JSON file")
    num_objects: int = doc(10, "Chemical: number of objects")
    cpt_seed: int = doc(0, "Chemical: seed of the fixed conditional probability tables (same for all workers)")


@dataclass(frozen=True)
class EnvEntry:
    """What Causeway knows about one environment."""

    name: str
    gym_id: str
    entry_point: str
    """``module:Class`` of the gymnasium environment (imported only when one is built)."""
    title: str
    options: tuple[str, ...] = ()
    """:class:`EnvOptions` fields passed to the constructor."""
    truth: str = "none"
    """Ground truth the env gives: ``global`` (``EnvSpec.global_graph``), ``local`` (``info["local_graph"]``
    every step), ``global+local`` or ``none``."""
    constant_factors: tuple[str, ...] = ()
    """Factors constant by construction: their columns are left out of the identifiable scores."""
    tasks: Mapping[str, str] = field(default_factory=dict)
    """Task name -> the registered environment that poses it (``--task``)."""
    skills: str = ""
    """``module:Class`` of the env's skill runner (a policy over skill options; ``""``: none). Its
    class attribute ``OPTION_NAMES`` lists the options, and, with ``skill_collection``, a uniform
    choice among them is the default collection policy."""
    skill_collection: bool = False
    evaluation: str = ""
    """Post-run evaluation suite that applies (``chemical``: chapter 3's k-step prediction and Match)."""
    check: Callable[[EnvOptions], None] | None = None
    """Validates the run options this env takes (``ValueError`` with a message), before anything starts."""

    @property
    def has_global_truth(self) -> bool:
        return self.truth in ("global", "global+local")

    @property
    def has_local_truth(self) -> bool:
        return self.truth in ("local", "global+local")

    def kwargs(self, options: EnvOptions) -> dict[str, Any]:
        """The constructor keyword arguments these run options give this env."""
        return {name: getattr(options, name) for name in self.options}

    def env_class(self) -> type[gym.Env]:
        return _load(self.entry_point)

    def make(self, **kwargs: Any) -> gym.Env:
        return self.env_class()(**kwargs)

    def skill_runner(self) -> type | None:
        return _load(self.skills) if self.skills else None


def _load(entry_point: str) -> Any:
    module, _, name = entry_point.partition(":")
    return getattr(importlib.import_module(module), name)


def _check_chemical(options: EnvOptions) -> None:
    from envs.graphs import load_dag

    load_dag(options.graph, options.num_objects)


_CHEMICAL = ("graph", "num_objects", "cpt_seed")

ENVS: dict[str, EnvEntry] = {e.name: e for e in (
    EnvEntry("chemical", "causeway/Chemical-v0", "envs.chemical:ChemicalEnv",
             "Chemical (ch. 3): coloured objects whose colours propagate along an object DAG",
             options=_CHEMICAL, truth="global+local", tasks={"match": "chemical-match"}, evaluation="chemical",
             check=_check_chemical),
    EnvEntry("chemical-match", "causeway/ChemicalMatch-v0", "envs.chemical_match:ChemicalMatchEnv",
             "Chemical with the Match task (ch. 3.3.5): reach the goal colours",
             options=_CHEMICAL, truth="global+local", tasks={"match": "chemical-match"}, evaluation="chemical",
             check=_check_chemical),
    EnvEntry("manipulation", "causeway/Manipulation-v0", "envs.manipulation:ManipulationEnv",
             "robosuite manipulation scene (ch. 3.3.1): UR5e, movable/fixed/random-walk cubes, markers",
             truth="global+local", constant_factors=manipulation_layout.CONSTANT_FACTORS,
             skills="envs.skills:SkillPolicy", skill_collection=True),
)}
"""Registered environments by name (the values ``--env`` takes)."""


def env_names() -> tuple[str, ...]:
    return tuple(ENVS)


def task_names() -> tuple[str, ...]:
    """Every task some environment poses, plus ``""`` (none): the values ``--task`` takes."""
    return ("",) + tuple(sorted({task for entry in ENVS.values() for task in entry.tasks}))


def env_entry(name: str) -> EnvEntry:
    """The entry of environment ``name``; unknown names raise ``KeyError`` listing the known ones."""
    try:
        return ENVS[name]
    except KeyError:
        raise KeyError(f"unknown environment {name!r}; known: {', '.join(ENVS)}") from None


def make_env(name: str, **kwargs: Any) -> gym.Env:
    """A new environment ``name`` built with ``kwargs``; unknown names raise ``KeyError``."""
    return env_entry(name).make(**kwargs)


def check_options(name: str, options: EnvOptions) -> None:
    """``ValueError`` if ``options`` cannot build environment ``name`` (unknown names: ``KeyError``)."""
    entry = env_entry(name)
    if entry.check is not None:
        entry.check(options)


def _register_with_gymnasium() -> None:
    for entry in ENVS.values():
        if entry.gym_id not in gym.registry:
            gym.register(id=entry.gym_id, entry_point=entry.entry_point)


_register_with_gymnasium()
assert {f.name for f in fields(EnvOptions)} >= {o for e in ENVS.values() for o in e.options}
