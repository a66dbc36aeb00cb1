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
from envs.distractors import parse_distractors
from proto.settings import doc

TRUTH_KINDS = ("global", "local", "global+local", "none")


def task_names() -> tuple[str, ...]:
    """Every task some environment poses, plus ``""`` (none): the values ``--task`` takes."""
    return ("",) + tuple(sorted({task for entry in ENVS.values() for task in entry.tasks}))


@dataclass(frozen=True)
class EnvOptions:
    """Environment construction options a run can set; each environment takes the ones it lists.

    For ``task``, ``episode_length``, ``room_size`` and ``velocities`` the empty value (``""``, 0,
    False) means the environment's own default and is not passed."""

    task: str = doc("", "task the environment poses ('' none: reward-free); a task may name another env "
                        "(Chemical's match: chemical-match); see each env's tasks in docs/environments.md",
                    choices=task_names)
    graph: str = doc("full", "Chemical object graph: collider, chain, full or a path to a DAG JSON file")
    num_objects: int = doc(10, "Chemical: number of objects")
    cpt_seed: int = doc(0, "Chemical: seed of the fixed conditional probability tables (same for all workers)")
    episode_length: int = doc(0, "steps per episode (0: the environment's default)")
    room_size: int = doc(0, "household tasks and 2D Minecraft: side of the room in cells (0: the env's default)")
    distractors: str = doc("20,20", "chapter 4's distractor factors, 'controllable,uncontrollable': random "
                                    "projections of the action and U(-1, 1) noise (chemical-distractors, block, tool-use, dmc-*)")
    velocities: bool = doc(False, "robosuite scenes (manipulation, block, tool-use): velocity factors for the arm, "
                                  "fingers and movable bodies, which make the state Markov (not the chapters' state; "
                                  "docs/environments.md)")

    def __post_init__(self) -> None:
        if self.episode_length < 0 or self.room_size < 0:
            raise ValueError("episode_length and room_size must be >= 0 (0: the environment's default)")
        parse_distractors(self.distractors)


DEFAULTED = ("task", "episode_length", "room_size", "velocities")
"""Options whose empty value means "the environment's default" (not passed to the constructor)."""


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
    """Task name -> the registered environment that poses it (``--task``; itself, or another env)."""
    task_kwarg: str = ""
    """Constructor keyword that takes the task name (``""``: the task is the env itself)."""
    skills: str = ""
    """``module:Class`` of the env's skill runner (a policy over skill options; ``""``: none). Its
    class attribute ``OPTION_NAMES`` lists the options, and, with ``skill_collection``, a uniform
    choice among them is the default collection policy."""
    skill_collection: bool = False
    local_scoring: bool = False
    """Whether runs score local-graph estimators here by default (the workers then send every step's
    true local graph; ``--worker-local-graphs true`` asks for it on any env with local truth)."""
    evaluation: str = ""
    """Post-run evaluation suite that applies (``chemical``: chapter 3's k-step prediction and Match)."""
    check: Callable[[EnvOptions], None] | None = None
    """Validates the run options this env takes (``ValueError`` with a message), before anything starts."""
    preset: Mapping[str, Any] = field(default_factory=dict)
    """Constructor keywords this entry always passes (``installing-printer-grid``: ``action_mode="grid"``)."""

    @property
    def has_global_truth(self) -> bool:
        return self.truth in ("global", "global+local")

    @property
    def has_local_truth(self) -> bool:
        return self.truth in ("local", "global+local")

    def kwargs(self, options: EnvOptions) -> dict[str, Any]:
        """The constructor keyword arguments these run options give this env."""
        out = {name: getattr(options, name) for name in self.options
               if not (name in DEFAULTED and not getattr(options, name))}
        if self.task_kwarg and options.task:
            out[self.task_kwarg] = options.task
        return out

    def env_class(self) -> type[gym.Env]:
        return _load(self.entry_point)

    def make(self, **kwargs: Any) -> gym.Env:
        return self.env_class()(**{**self.preset, **kwargs})

    def skill_runner(self) -> type | None:
        return _load(self.skills) if self.skills else None


def _load(entry_point: str) -> Any:
    module, _, name = entry_point.partition(":")
    return getattr(importlib.import_module(module), name)


def _check_chemical(options: EnvOptions) -> None:
    from envs.graphs import load_dag

    load_dag(options.graph, options.num_objects)


def _check_by_building(entry_name: str) -> Callable[[EnvOptions], None]:
    """An option check that builds the (cheap) environment: its constructor validates everything."""
    def check(options: EnvOptions) -> None:
        entry = ENVS[entry_name]
        entry.make(**entry.kwargs(options)).close()
    return check


def _check_dmc(entry_name: str) -> Callable[[EnvOptions], None]:
    """Build the env (cheap), so a missing ``dm_control`` is refused before anything starts, as a ``ValueError``."""
    build = _check_by_building(entry_name)

    def check(options: EnvOptions) -> None:
        try:
            build(options)
        except ImportError as exc:
            raise ValueError(str(exc)) from None
    return check


_CHEMICAL = ("graph", "num_objects", "cpt_seed", "episode_length")
_GRID = ("episode_length", "room_size")
_THAWING = ("thaw-fish", "thaw-olive", "thaw-date", "thaw-all")
_CLEANING = ("soak-rag", "clean-car", "clean-rag")
_MINECRAFT = ("wood", "stick", "wood_pickaxe", "stone", "stone_pickaxe", "iron_ore", "iron", "iron_pickaxe", "diamond")
_HOUSEHOLD = dict(truth="global+local", local_scoring=True)

ENVS: dict[str, EnvEntry] = {e.name: e for e in (
    EnvEntry("chemical", "causeway/Chemical-v0", "envs.chemical:ChemicalEnv",
             "Chemical (ch. 3): coloured objects whose colours propagate along an object DAG",
             options=_CHEMICAL, truth="global+local", tasks={"match": "chemical-match"}, evaluation="chemical",
             check=_check_chemical),
    EnvEntry("chemical-match", "causeway/ChemicalMatch-v0", "envs.chemical_match:ChemicalMatchEnv",
             "Chemical with the Match task (ch. 3.3.5): reach the goal colours",
             options=_CHEMICAL, truth="global+local", tasks={"match": "chemical-match"}, evaluation="chemical",
             check=_check_chemical),
    EnvEntry("chemical-distractors", "causeway/ChemicalDistractors-v0",
             "envs.chemical_distractors:ChemicalDistractorsEnv",
             "Chemical Match with chapter 4's controllable and uncontrollable distractors (CBM)",
             options=_CHEMICAL + ("distractors",), truth="global+local",
             tasks=dict.fromkeys(("match", "match-first"), "chemical-distractors"), task_kwarg="task",
             check=_check_chemical),
    EnvEntry("chemical-pixels", "causeway/ChemicalPixels-v0", "envs.chemical_pixels:ChemicalPixelsEnv",
             "Chemical drawn as RGB frames with exact per-object masks in info (ch. 7, Dyn-O's rendered env)",
             options=_CHEMICAL, truth="global+local", check=_check_chemical),
    EnvEntry("chemical-pixels-two-tone", "causeway/ChemicalPixelsTwoTone-v0", "envs.chemical_pixels:ChemicalPixelsEnv",
             "chemical-pixels with every shape's lower half in one grey shared by all objects: objects of two parts "
             "(ch. 7, Table 7.1)", options=_CHEMICAL, truth="global+local", check=_check_chemical,
             preset={"two_tone": True}),
    EnvEntry("manipulation", "causeway/Manipulation-v0", "envs.manipulation:ManipulationEnv",
             "robosuite manipulation scene (ch. 3.3.1): UR5e, movable/fixed/random-walk cubes, markers",
             options=("episode_length", "velocities"), truth="global+local",
             constant_factors=manipulation_layout.CONSTANT_FACTORS,
             skills="envs.skills:SkillPolicy", skill_collection=True, local_scoring=True),
    EnvEntry("block", "causeway/Block-v0", "envs.block:BlockEnv",
             "chapter 4's block scene (CBM): UR5e, movable mov1-mov3, fixed unm, 20+20 distractors; Pick, Stack",
             options=("episode_length", "distractors", "velocities"), truth="global+local",
             constant_factors=manipulation_layout.BLOCK.constant_factors,
             tasks=dict.fromkeys(("pick", "stack"), "block"), task_kwarg="task", local_scoring=True),
    EnvEntry("tool-use", "causeway/ToolUse-v0", "envs.tool_use:ToolUseEnv",
             "chapter 4's tool-use scene (CBM): UR5e, an L-shaped tool, a block out of reach, a fixed open box, "
             "20+20 distractors; Series",
             options=("episode_length", "distractors", "velocities"), truth="global+local",
             constant_factors=manipulation_layout.TOOL_USE.constant_factors,
             tasks={"series": "tool-use"}, task_kwarg="task", local_scoring=True),
    EnvEntry("dmc-walker", "causeway/DMCWalker-v0", "envs.dmc:WalkerEnv",
             "DeepMind Control Suite Walker with 20+20 distractors (ch. 4, Fig. 4.7); needs dm_control",
             options=("episode_length", "distractors"), truth="global",
             tasks=dict.fromkeys(("walk", "stand", "run"), "dmc-walker"), task_kwarg="task",
             check=_check_dmc("dmc-walker")),
    EnvEntry("dmc-cheetah", "causeway/DMCCheetah-v0", "envs.dmc:CheetahEnv",
             "DeepMind Control Suite Cheetah with 20+20 distractors (ch. 4, Fig. 4.7); needs dm_control",
             options=("episode_length", "distractors"), truth="global",
             tasks={"run": "dmc-cheetah"}, task_kwarg="task", check=_check_dmc("dmc-cheetah")),
    EnvEntry("installing-printer", "causeway/InstallingPrinter-v0", "envs.household.printer:InstallingPrinterEnv",
             "Mini-BEHAVIOR Installing Printer (ch. 6): pick the printer, put it on the table, turn it on",
             options=_GRID, constant_factors=("table.clean",), check=_check_by_building("installing-printer"),
             **_HOUSEHOLD),
    EnvEntry("thawing", "causeway/Thawing-v0", "envs.household.thawing:ThawingEnv",
             "Mini-BEHAVIOR Thawing (ch. 5-6): thaw the fish, olive or date from the fridge in the sink",
             options=_GRID, tasks=dict.fromkeys(_THAWING, "thawing"), task_kwarg="task",
             check=_check_by_building("thawing"), **_HOUSEHOLD),
    EnvEntry("cleaning-car", "causeway/CleaningCar-v0", "envs.household.cleaning_car:CleaningCarEnv",
             "Mini-BEHAVIOR Cleaning Car (ch. 6; CarWash of ch. 5): soak the rag, clean the car, clean the rag",
             options=_GRID, tasks=dict.fromkeys(_CLEANING, "cleaning-car"), task_kwarg="task",
             check=_check_by_building("cleaning-car"), **_HOUSEHOLD),
    *(EnvEntry(f"{name}-grid", gym_id.replace("-v0", "Grid-v0"), point,
               f"{title}; Mini-BEHAVIOR's cell-by-cell actions (left, right, forward, object actions in front) "
               "instead of goTo primitives", options=_GRID, constant_factors=constant,
               tasks=dict.fromkeys(tasks, f"{name}-grid"), task_kwarg="task" if tasks else "",
               check=_check_by_building(f"{name}-grid"), preset={"action_mode": "grid"}, **_HOUSEHOLD)
      for name, gym_id, point, title, constant, tasks in (
          ("installing-printer", "causeway/InstallingPrinter-v0", "envs.household.printer:InstallingPrinterEnv",
           "Mini-BEHAVIOR Installing Printer (ch. 6)", ("table.clean",), ()),
          ("thawing", "causeway/Thawing-v0", "envs.household.thawing:ThawingEnv", "Mini-BEHAVIOR Thawing (ch. 5-6)",
           (), _THAWING),
          ("cleaning-car", "causeway/CleaningCar-v0", "envs.household.cleaning_car:CleaningCarEnv",
           "Mini-BEHAVIOR Cleaning Car (ch. 6)", (), _CLEANING))),
    EnvEntry("minecraft2d", "causeway/Minecraft2D-v0", "envs.minecraft2d:Minecraft2DEnv",
             "2D Minecraft (ch. 5, after Andreas et al. 2017): gather and craft up a technology tree",
             options=_GRID, tasks=dict.fromkeys(_MINECRAFT, "minecraft2d"), task_kwarg="goal",
             check=_check_by_building("minecraft2d"), **_HOUSEHOLD),
    EnvEntry("sprites", "causeway/Sprites-v0", "envs.sprites:SpritesEnv",
             "a bigfish-like sprite game drawn as RGB frames with exact occlusion-aware masks (ch. 7, Dyn-O)",
             options=("episode_length",), truth="local", constant_factors=("agent.vx", "agent.color"),
             check=_check_by_building("sprites")),
    EnvEntry("multigrid-agents", "causeway/MultiGridAgents-v0", "envs.multigrid_agents:MultiGridAgentsEnv",
             "MultiGrid agents drawn as RGB frames (ch. 8, FLAM): 4 agents acting independently, exact masks",
             options=("episode_length",)),
    EnvEntry("multigrid-agents-correlated", "causeway/MultiGridAgentsCorrelated-v0",
             "envs.multigrid_agents:CorrelatedMultiGridAgentsEnv",
             "MultiGrid agents, correlated variant (ch. 8.3): agent 1 repeats agent 0's action",
             options=("episode_length",)),
)}
"""Registered environments by name (the values ``--env`` takes)."""


def env_names() -> tuple[str, ...]:
    return tuple(ENVS)


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
    """``ValueError`` if ``options`` cannot build environment ``name`` (unknown names: ``KeyError``),
    or set an option away from its default that this environment does not take (it would be ignored)."""
    entry = env_entry(name)
    unused = [f.name for f in fields(EnvOptions) if f.name != "task" and f.name not in entry.options
              and getattr(options, f.name) != f.default]
    if unused:
        flags = ", ".join("--" + o.replace("_", "-") for o in unused)
        takes = ", ".join("--" + o.replace("_", "-") for o in entry.options) or "none"
        raise ValueError(f"environment {name!r} does not take {flags} (its options: {takes})")
    if entry.check is not None:
        entry.check(options)


def _register_with_gymnasium() -> None:
    for entry in ENVS.values():
        if entry.gym_id not in gym.registry:
            gym.register(id=entry.gym_id, entry_point=entry.entry_point, kwargs=dict(entry.preset))


_register_with_gymnasium()
assert {f.name for f in fields(EnvOptions)} >= {o for e in ENVS.values() for o in e.options}
