"""Frozen config dataclasses mapped one-to-one onto CLI flags and environment variables.

Field ``metrics_port`` is set by ``--metrics-port`` or ``CAUSEWAY_METRICS_PORT``; a flag wins over
the environment, the environment over the default. Help text comes from ``field(metadata={"help"})``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence, TypeVar, get_type_hints

T = TypeVar("T")
ENV_PREFIX = "CAUSEWAY_"


def doc(default: Any, help: str) -> Any:
    """A dataclass field with a default and a help text."""
    return field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class ServiceConfig:
    """Fields every service has."""

    run_id: str = doc("default", "run id: the <run> segment of every topic")
    zenoh_connect: str = doc("tcp/127.0.0.1:7447", "Zenoh router endpoint to connect to")
    metrics_port: int = doc(0, "port of the Prometheus /metrics endpoint (0: none)")
    run_dir: str = doc("runs/default", "run directory: checkpoints, logs, summaries")
    instance: str = doc("0", "instance id of this process within its service")
    stats_interval_s: float = doc(1.0, "seconds between progress beats on the stats topic")


def _parse_bool(text: str) -> bool:
    lowered = text.strip().lower()
    if lowered in ("1", "true", "yes", "on"):
        return True
    if lowered in ("0", "false", "no", "off"):
        return False
    raise ValueError(f"not a boolean: {text!r}")


def _converter(tp: Any):
    if tp is bool:
        return _parse_bool
    if tp in (int, float, str):
        return tp
    raise TypeError(f"unsupported config field type {tp!r}")


def parse_config(cls: type[T], argv: Sequence[str] | None = None,
                 environ: Mapping[str, str] | None = None) -> T:
    """Build ``cls`` from defaults, then ``CAUSEWAY_<FIELD>`` variables, then ``--field`` flags."""
    environ = os.environ if environ is None else environ
    hints = get_type_hints(cls)
    parser = argparse.ArgumentParser(description=(cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else None)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        convert = _converter(hints[f.name])
        env_key = ENV_PREFIX + f.name.upper()
        if env_key in environ:
            try:
                values[f.name] = convert(environ[env_key])
            except ValueError as exc:
                raise SystemExit(f"invalid {env_key}={environ[env_key]!r}: {exc}") from None
        parser.add_argument("--" + f.name.replace("_", "-"), dest=f.name, type=convert, default=None,
                            help=f"{f.metadata.get('help', '')} (env {env_key}, default {f.default!r})")
    args = parser.parse_args(list(argv) if argv is not None else None)
    values.update({k: v for k, v in vars(args).items() if v is not None})
    return cls(**values)


def write_config(cfg: Any, path: Path) -> None:
    """The effective config, as JSON, into the run directory."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(dataclasses.asdict(cfg), indent=2, sort_keys=True) + "\n")


def to_environ(cfg: Any) -> dict[str, str]:
    """The inverse of ``parse_config``: environment variables that reproduce ``cfg``."""
    out = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        out[ENV_PREFIX + f.name.upper()] = ("true" if value else "false") if isinstance(value, bool) else str(value)
    return out
