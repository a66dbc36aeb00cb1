"""Gymnasium environments with a factored-state contract and ground-truth graphs.

Services build environments by name with :func:`make_env`; each environment's constructor keyword
arguments are its configuration (e.g. ``make_env("chemical", graph="chain", num_objects=5)``).
Factories import their module lazily, so a heavy simulator is only loaded when asked for.
"""
from __future__ import annotations

from typing import Any, Callable

import gymnasium as gym


def _chemical(**kwargs: Any) -> gym.Env:
    from envs.chemical import ChemicalEnv

    return ChemicalEnv(**kwargs)


def _chemical_match(**kwargs: Any) -> gym.Env:
    from envs.chemical_match import ChemicalMatchEnv

    return ChemicalMatchEnv(**kwargs)


def _manipulation(**kwargs: Any) -> gym.Env:
    from envs.manipulation import ManipulationEnv

    return ManipulationEnv(**kwargs)


ENV_FACTORIES: dict[str, Callable[..., gym.Env]] = {
    "chemical": _chemical, "chemical-match": _chemical_match, "manipulation": _manipulation}


def make_env(name: str, **kwargs: Any) -> gym.Env:
    """A new environment ``name`` built with ``kwargs``; unknown names raise ``KeyError``."""
    try:
        factory = ENV_FACTORIES[name]
    except KeyError:
        raise KeyError(f"unknown environment {name!r}; known: {sorted(ENV_FACTORIES)}") from None
    return factory(**kwargs)
