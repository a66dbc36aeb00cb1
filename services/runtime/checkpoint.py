"""Checkpoints: atomic writes of CPU tensors, and loads that never unpickle arbitrary objects
(weights_only=True) and put every tensor on the CPU (a checkpoint written on a GPU loads without one)."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import torch


CONFIG_ERROR_EXIT = 78
"""Exit code (EX_CONFIG) of a service that must not be restarted as it is: the supervisor gives up."""


class CheckpointMismatch(ValueError):
    """The run directory holds a checkpoint made for another environment or model configuration."""


def check_fingerprint(saved: dict[str, Any], fingerprint: str, path: Path) -> None:
    """Refuse to resume from a checkpoint whose environment/model fingerprint (JSON) differs from ours."""
    theirs = saved.get("fingerprint")
    if theirs == fingerprint:
        return
    try:
        old, new = _flatten(json.loads(theirs)), _flatten(json.loads(fingerprint))
        changes = ", ".join(f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in sorted(set(old) | set(new))
                            if old.get(k) != new.get(k))
    except (TypeError, ValueError):
        changes = "the checkpoint has no readable fingerprint"
    raise CheckpointMismatch(f"{path} was written for a different environment or model configuration ({changes}); "
                             "use a new --run-dir, or resume with the run's own config.json")


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        return {k: v for key, item in value.items() for k, v in _flatten(item, f"{prefix}{key}.").items()}
    return {prefix.rstrip("."): value}


def save_checkpoint(state: dict[str, Any], path: Path) -> None:
    """Write ``state`` to ``path`` atomically: a crash mid-write leaves the previous checkpoint intact."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    os.close(fd)
    try:
        torch.save(on_cpu(state), tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def load_checkpoint(path: Path) -> dict[str, Any] | None:
    """The saved state, or None when there is none. Tensors, numbers, strings and containers only."""
    if not path.exists():
        return None
    return torch.load(path, weights_only=True, map_location="cpu")


def on_cpu(value: Any) -> Any:
    """``value`` with every tensor in it (through dicts, lists and tuples) on the CPU; CPU tensors are
    returned as they are, not copied."""
    if isinstance(value, torch.Tensor):
        return value.cpu()
    if isinstance(value, dict):
        return {key: on_cpu(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(on_cpu(item) for item in value)
    return value
