"""Field helpers for settings dataclasses: help text, allowed values, nested sections.

Settings cross process boundaries too: a service's configuration travels to its process as
``CAUSEWAY_*`` environment variables and lands in the run directory as JSON. Every layer declares
its settings with these helpers (a method's hyper-parameters in ``causal/``, an environment's
constructor options in ``envs/``, a service's in ``services/``), and ``services.runtime.config``
turns any such dataclass into flags and environment variables. Nothing here imports above ``proto``.

* ``doc(default, help, choices=...)``: a field with a help text and, optionally, its allowed values
  (a tuple, or a function returning one, so that a registry can be read when the flags are built).
* ``section(cls, prefix, exclude=(), **defaults)``: a field holding another settings dataclass whose
  fields become flags named ``--<prefix>-<field>`` (``prefix=""``: unprefixed). ``exclude`` names
  fields that are not flags (the wiring sets them); ``defaults`` override the class's defaults.
"""
from __future__ import annotations

from dataclasses import field, fields
from typing import Any, Callable

Choices = tuple[str, ...] | Callable[[], tuple[str, ...]]


def doc(default: Any, help: str, choices: Choices | None = None) -> Any:
    """A dataclass field with a default, a help text and optionally its allowed values."""
    metadata: dict[str, Any] = {"help": help}
    if choices is not None:
        metadata["choices"] = choices
    return field(default=default, metadata=metadata)


def section(cls: type, prefix: str, exclude: tuple[str, ...] = (), help: str = "", **defaults: Any) -> Any:
    """A dataclass field holding a ``cls`` instance whose fields are flags ``--<prefix>-<name>``."""
    return field(default_factory=lambda: cls(**defaults),
                 metadata={"section": prefix, "exclude": tuple(exclude), "help": help or (cls.__doc__ or "")})


def choices_of(metadata: Any) -> tuple[str, ...] | None:
    """The allowed values a field declares (calling the registry function if it is one), or None."""
    choices = metadata.get("choices")
    if choices is None:
        return None
    return tuple(choices() if callable(choices) else choices)


def check_choices(settings: Any) -> None:
    """``ValueError`` naming the field and its allowed values if one of ``settings``' fields (not its
    sections) holds a value its ``doc(..., choices=...)`` does not allow."""
    for f in fields(settings):
        allowed = choices_of(f.metadata)
        value = getattr(settings, f.name)
        if allowed is not None and value not in allowed:
            raise ValueError(f"{f.name} must be one of {', '.join(repr(c) for c in allowed)}; got {value!r}")
