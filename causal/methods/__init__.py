"""The method registry: a method name -> the module that builds its :class:`causal.method.Method`.

Adding a method is a module under ``causal/methods/`` defining ``METHOD`` (a
:class:`causal.method.Method`) and one line in :data:`METHODS`. Modules are imported when a method is first asked for, so listing the names (for
validating ``--method``) costs nothing. ``docs/architecture.md`` walks through adding one.
"""
from __future__ import annotations

import dataclasses
import functools
import importlib
import json
from typing import Any

from torch import nn

from causal.method import Method
from proto.settings import section

METHODS: dict[str, str] = {
    "cdl": "causal.methods.cdl",
    "elden": "causal.methods.elden",
    "modular": "causal.methods.dense:MODULAR",
    "monolithic": "causal.methods.dense:MONOLITHIC",
    "cbm": "causal.methods.cbm",
    "skild": "causal.methods.skild",
    "dyno": "causal.methods.dyno",
    "flam": "causal.methods.flam",
}
"""Registered methods: name -> ``module`` defining ``METHOD`` (or ``module:NAME``)."""

_EXTRA: dict[str, Method] = {}


def method_names() -> tuple[str, ...]:
    """Every registered method's name (the values ``--method`` takes)."""
    return tuple(METHODS) + tuple(name for name in _EXTRA if name not in METHODS)


def get_method(name: str) -> Method:
    """The registered method ``name``; unknown names raise ``KeyError`` listing the known ones."""
    if name in _EXTRA:
        return _EXTRA[name]
    if name not in METHODS:
        raise KeyError(f"unknown method {name!r}; known: {', '.join(method_names())}")
    module, _, attribute = METHODS[name].partition(":")
    return getattr(importlib.import_module(module), attribute or "METHOD")


def register(method: Method) -> None:
    """Register ``method`` at run time (tests, plug-ins outside this repository)."""
    _EXTRA[method.name] = method


def unregister(name: str) -> None:
    _EXTRA.pop(name, None)


@functools.cache
def method_configs_class() -> type:
    """A frozen dataclass with one section per method in :data:`METHODS` (flags ``--<method>-<field>``):
    every method's hyper-parameters, declared once in the method's own config class."""
    fields = [(name, get_method(name).config, section(get_method(name).config, prefix=name))
              for name in METHODS]
    return dataclasses.make_dataclass("MethodConfigs", fields, frozen=True)


def method_config(models: Any, name: str) -> Any:
    """The settings of method ``name`` in a ``MethodConfigs`` (its defaults where it has no section)."""
    return getattr(models, name, None) or get_method(name).config()


def model_from_config_json(text: str) -> nn.Module:
    """Rebuild the model a ``Weights.config_json`` describes, through the method it names."""
    data = json.loads(text)
    name = data.get("model")
    if not isinstance(name, str):
        raise ValueError("model config names no method")
    return get_method(name).model_from_config(data)
