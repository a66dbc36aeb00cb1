"""Gymnasium environments with a factored-state contract and ground-truth graphs.

Services build environments by name with :func:`make_env`; each environment's constructor keyword
arguments are its configuration (e.g. ``make_env("chemical", graph="chain", num_objects=5)``).
What Causeway knows about each environment (options, ground truth, tasks, skills) is its entry in
:mod:`envs.registry`; environment modules are imported only when one is built.
"""
from __future__ import annotations

from envs.registry import ENVS, EnvEntry, EnvOptions, env_entry, make_env

__all__ = ["ENVS", "EnvEntry", "EnvOptions", "env_entry", "make_env"]
