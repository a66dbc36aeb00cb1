"""Frozen config dataclasses mapped one-to-one onto CLI flags and environment variables.

Field ``metrics_port`` is set by ``--metrics-port`` or ``CAUSEWAY_METRICS_PORT``; a flag wins over
the environment, the environment over the default. Help text and allowed values come from
``proto.settings.doc``. A field declared with ``proto.settings.section`` holds another settings
dataclass whose fields are flags too, named ``--<prefix>-<field>`` (``CAUSEWAY_<PREFIX>_<FIELD>``):
that is how a run composes the services' and methods' settings, each declared once, in its owner.

Bad values (unparsable, not among a field's allowed values, refused by the dataclass's own checks)
end the program with exit status 2 and a message naming the flag and, for enumerations, the valid
values: before anything starts.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence, TypeVar, get_type_hints

from proto.settings import check_choices, choices_of, doc

__all__ = ["ENV_PREFIX", "Flag", "RunSettings", "ServiceConfig", "build_config", "config_from_dict", "doc", "flags", "parse_config",
           "settings_parser", "to_environ", "write_config", "USAGE_EXIT"]

T = TypeVar("T")
ENV_PREFIX = "CAUSEWAY_"
USAGE_EXIT = 2
"""Exit status of a command refused for its flags or settings (argparse's own)."""


def _method_names() -> tuple[str, ...]:
    from causal.methods import method_names  # the names only: no method module is imported

    return method_names()


@dataclass(frozen=True)
class RunSettings:
    """Settings of a run that every service shares: the supervisor gives each service the same values."""

    method: str = doc("cdl", "causal method (causal.methods): what the learner trains, the evaluator "
                             "estimates and the policy abstracts with; names the weights/<method> and "
                             "graph/<method> topics", choices=_method_names)
    seed: int = doc(0, "run seed: every service seeds its random sources from it (env-worker i uses seed + i)")
    heldout_fraction: float = doc(0.1, "fraction of episodes held out from training, for graph estimation "
                                       "(the learner and the evaluator split episodes the same way)")
    checkpoint_every_s: float = doc(30.0, "seconds between service checkpoints")
    device: str = doc("auto", "where the processes that train or evaluate a model run them: auto (cuda if torch "
                              "sees one and the method runs there, else cpu), cpu, or cuda (refused where there "
                              "is none); weights and checkpoints are device-independent", choices=("auto", "cpu", "cuda"))

    def __post_init__(self) -> None:
        check_choices(self)
        if not 0.0 <= self.heldout_fraction < 1.0:
            raise ValueError(f"heldout_fraction must be in [0, 1), got {self.heldout_fraction}")
        if not self.checkpoint_every_s > 0:
            raise ValueError(f"checkpoint_every_s must be > 0, got {self.checkpoint_every_s}")


@dataclass(frozen=True)
class ServiceConfig(RunSettings):
    """Fields every service has: the run-wide settings and where this process sits in the run."""

    run_id: str = doc("default", "run id: the <run> segment of every topic")
    zenoh_connect: str = doc("tcp/127.0.0.1:7447", "Zenoh router endpoint to connect to")
    metrics_port: int = doc(0, "port of the Prometheus /metrics endpoint (0: none)")
    metrics_host: str = doc("0.0.0.0", "address the /metrics endpoint binds to (the local stack: 127.0.0.1; a "
                                       "container: every interface, for Prometheus on the compose network)")
    run_dir: str = doc("runs/default", "run directory: checkpoints, logs, summaries")
    instance: str = doc("0", "instance id of this process within its service")
    stats_interval_s: float = doc(1.0, "seconds between progress beats on the stats topic")
    bus_credentials: str = doc("", "file holding this process's Zenoh user and password (one line user:password; "
                                   "a compose or Kubernetes secret, or <run_dir>/secrets/<role>.credentials of a "
                                   "local run with --bus-auth); empty: connect without credentials")
    bus_tls_root_ca: str = doc("", "CA certificate (PEM file) that signed the router's TLS certificate, to reach a "
                                   "router on a tls/HOST:PORT endpoint (links that leave a host); empty: none")
    known_version: int = doc(-1, "a version of the weights this process consumes (the dynamics-learner's; an "
                                 "env-worker's: the policy-learner's) known published before it started, as the local "
                                 "supervisor read it; a publisher's first version may exceed it (or this process's "
                                 "checkpointed one) by at most 10,000 (services/runtime/accept.py); -1: none known "
                                 "(compose, Kubernetes: no supervisor reads the learner's record), the first version "
                                 "is taken as it comes unless a checkpoint gives one")


SERVICE_FIELDS = tuple(f.name for f in dataclasses.fields(ServiceConfig))
"""Fields the wiring sets for every service (never flags of a run's service section)."""


@dataclass(frozen=True)
class Flag:
    """One settings field as a flag: where it sits in the (nested) config and how it is spelled."""

    path: tuple[str, ...]
    name: str
    """Flag without its dashes, e.g. ``cdl-lr``."""
    type: Any
    default: Any
    help: str
    choices: tuple[str, ...] | None
    group: str = ""
    """Title of the section the flag comes from ('' for the top level)."""

    @property
    def env(self) -> str:
        return ENV_PREFIX + self.name.replace("-", "_").upper()


def _is_section(f: dataclasses.Field) -> bool:
    return "section" in f.metadata


def flags(cls: type, default: Any = None) -> list[Flag]:
    """Every flag of ``cls``, sections flattened, with the defaults of ``default`` (``cls()``)."""
    return _flags(cls, cls() if default is None else default, (), (), (), "")


def _flags(cls: type, default: Any, path: tuple[str, ...], prefix: tuple[str, ...],
           exclude: tuple[str, ...], group: str) -> list[Flag]:
    hints = get_type_hints(cls)
    out: list[Flag] = []
    for f in dataclasses.fields(cls):
        if f.name in exclude:
            continue
        value = getattr(default, f.name)
        if _is_section(f):
            sub = prefix + ((f.metadata["section"],) if f.metadata["section"] else ())
            title = (f.metadata["help"].strip().splitlines() or [f.name])[0].rstrip(".")
            title += f" (--{'-'.join(sub)}-*)" if sub else ""
            out += _flags(hints[f.name], value, path + (f.name,), sub, f.metadata["exclude"], title)
        else:
            name = "-".join(prefix + (f.name.replace("_", "-"),))
            out.append(Flag(path + (f.name,), name, hints[f.name], value, f.metadata.get("help", ""),
                            choices_of(f.metadata), group))
    return out


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


def settings_parser(cls: type, prog: str | None = None) -> tuple[argparse.ArgumentParser, list[Flag]]:
    """The argparse parser of ``cls``'s flags (no abbreviations), and the flags it holds."""
    description = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else None
    parser = argparse.ArgumentParser(prog=prog, description=description, allow_abbrev=False,
                                     usage="%(prog)s [--help] [--FLAG VALUE ...]")
    table = flags(cls)
    groups: dict[str, Any] = {}
    for flag in table:
        if flag.group not in groups:
            groups[flag.group] = parser.add_argument_group(flag.group) if flag.group else parser
        values = f"; one of {', '.join(repr(c) for c in flag.choices)}" if flag.choices else ""
        groups[flag.group].add_argument(
            "--" + flag.name, dest=flag.name, type=_converter(flag.type), default=None,
            metavar=flag.type.__name__.upper(), help=f"{flag.help}{values} (env {flag.env}, default {flag.default!r})")
    return parser, table


def parse_config(cls: type[T], argv: Sequence[str] | None = None,
                 environ: Mapping[str, str] | None = None, prog: str | None = None) -> T:
    """Build ``cls`` from defaults, then ``CAUSEWAY_<FLAG>`` variables, then ``--flag`` flags.

    Any refused value ends the program (``SystemExit``, status 2) with a message naming it."""
    environ = os.environ if environ is None else environ
    parser, table = settings_parser(cls, prog)
    args = vars(parser.parse_args(list(argv) if argv is not None else None))
    values: dict[tuple[str, ...], Any] = {}
    for flag in table:
        if args[flag.name] is not None:
            values[flag.path] = args[flag.name]
        elif flag.env in environ:
            try:
                values[flag.path] = _converter(flag.type)(environ[flag.env])
            except ValueError as exc:
                parser.exit(USAGE_EXIT, f"{parser.prog}: error: invalid {flag.env}={environ[flag.env]!r}: {exc}\n")
        if flag.choices is not None and flag.path in values and values[flag.path] not in flag.choices:
            parser.error(f"argument --{flag.name}: invalid choice {values[flag.path]!r} "
                         f"(choose from {', '.join(repr(c) for c in flag.choices)})")
    try:
        return _build(cls, cls(), values, ())
    except ValueError as exc:
        parser.error(str(exc))
        raise  # unreachable: parser.error exits


def _build(cls: type, default: Any, values: Mapping[tuple[str, ...], Any], path: tuple[str, ...]) -> Any:
    hints = get_type_hints(cls)
    changes = {}
    for f in dataclasses.fields(cls):
        here = path + (f.name,)
        if _is_section(f):
            changes[f.name] = _build(hints[f.name], getattr(default, f.name), values, here)
        elif here in values:
            changes[f.name] = values[here]
    return dataclasses.replace(default, **changes) if changes else default


def build_config(cls: type[T], **settings: Any) -> T:
    """``cls`` with settings named as their flags (``_`` for ``-``): the Python twin of the command line,
    ``build_config(RunConfig, graph="chain", cdl_lr=1e-3, policy_hide="mk")`` is ``--graph chain
    --cdl-lr 0.001 --policy-hide mk``. An unknown name raises ``TypeError``; a refused value ``ValueError``."""
    table = {flag.name.replace("-", "_"): flag.path for flag in flags(cls)}
    unknown = sorted(set(settings) - set(table))
    if unknown:
        raise TypeError(f"{cls.__name__} has no setting {', '.join(unknown)}")
    return _build(cls, cls(), {table[name]: value for name, value in settings.items()}, ())


def config_from_dict(cls: type[T], data: Mapping[str, Any]) -> T:
    """Rebuild ``cls`` from its ``write_config`` JSON. Keys it no longer has are matched to flags of
    the same name (a setting that moved into a section), else ignored; missing ones take defaults."""
    values: dict[tuple[str, ...], Any] = {}
    by_name = {flag.name.replace("-", "_"): flag.path for flag in flags(cls)}

    def walk(sub: type, node: Mapping[str, Any], path: tuple[str, ...]) -> None:
        hints = get_type_hints(sub)
        names = {f.name: f for f in dataclasses.fields(sub)}
        for key, value in node.items():
            f = names.get(key)
            if f is not None and _is_section(f) and isinstance(value, Mapping):
                walk(hints[key], value, path + (key,))
            elif f is not None:
                values[path + (key,)] = value
            elif not path and key in by_name:
                values[by_name[key]] = value

    walk(cls, data, ())
    return _build(cls, cls(), values, ())


def write_config(cfg: Any, path: Path) -> None:
    """The effective config, as JSON, into the run directory."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(dataclasses.asdict(cfg), indent=2, sort_keys=True) + "\n")


def to_environ(cfg: Any) -> dict[str, str]:
    """The inverse of ``parse_config``: environment variables that reproduce ``cfg`` (every flag)."""
    out = {}
    for flag in flags(type(cfg), cfg):
        value = flag.default
        out[flag.env] = ("true" if value else "false") if isinstance(value, bool) else str(value)
    return out
