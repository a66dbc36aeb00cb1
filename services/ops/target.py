"""Which run an operator command talks to, and the bus session it talks over.

A run is named by its router endpoint and run id: ``--connect tcp/127.0.0.1:7447 --run RUN_ID``, or
``--run-dir runs/X`` for a local run, whose ``processes.json`` holds the router endpoint and whose
``config.json`` holds the run id (and the router port, used while ``processes.json`` is not there
yet). Explicit flags win over the run directory, which wins over ``CAUSEWAY_ZENOH_CONNECT`` /
``CAUSEWAY_RUN_ID``; the endpoint falls back to the local default router.

Credentials (a router with roles, :mod:`services.bus.roles`): ``--bus-credentials FILE``, else the run
directory's ``secrets/operator.credentials`` where its ``config.json`` says ``bus_auth``, else
``$CAUSEWAY_BUS_CREDENTIALS``; none of them: the command connects without credentials (a router
without authentication refuses a client that brings some, and one with it a client that brings none).
"""
from __future__ import annotations

import argparse
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

from proto import topics
from services.bus.credentials import Credentials, read_credentials, role_file
from services.bus.router import LOOPBACK_ROUTER
from services.bus.zenoh_transport import ZenohTransport

EXIT_UNREACHABLE = 2
"""Exit status of a command that could not reach the router or the Docker engine, or was misused."""
EXIT_NOT_CONFIRMED = 1
"""Exit status of a command that was sent but whose effect was not seen in time."""


SCALABLE = ("env-worker",)
"""Services an operator may scale; the others own state (checkpoints, replay)."""


class OpsError(Exception):
    """A command that cannot go on: the message is for the operator, ``exit_code`` for the shell."""

    def __init__(self, message: str, exit_code: int = EXIT_UNREACHABLE) -> None:
        super().__init__(message)
        self.exit_code = exit_code


@dataclass(frozen=True)
class Target:
    """One run on one router."""

    connect: str
    """Zenoh endpoint of the run's router, e.g. ``tcp/127.0.0.1:7447``."""
    run_id: str
    """The ``<run>`` segment of every topic of the run."""
    credentials: Credentials | None = None
    """The operator's bus credentials, where the router requires them."""
    root_ca: str = ""
    """CA certificate that signed a ``tls/`` router's certificate ('' for ``tcp/``)."""


def add_target_arguments(parser: argparse.ArgumentParser) -> None:
    """``--connect``, ``--run`` and ``--run-dir``."""
    parser.add_argument("--connect", default=None,
                        help=f"Zenoh router endpoint (default: the run dir's router, else $CAUSEWAY_ZENOH_CONNECT, "
                             f"else {LOOPBACK_ROUTER})")
    parser.add_argument("--run", dest="run_id", default=None,
                        help="run id (default: the run dir's, else $CAUSEWAY_RUN_ID)")
    parser.add_argument("--run-dir", default=None,
                        help="a local run directory: router endpoint from processes.json, run id from config.json, "
                             "operator credentials from secrets/operator.credentials (a run with --bus-auth)")
    parser.add_argument("--bus-credentials", default=None,
                        help="file with the operator's bus credentials, one line user:password (default: the run "
                             "dir's, else $CAUSEWAY_BUS_CREDENTIALS, else none)")
    parser.add_argument("--bus-tls-root-ca", default=None,
                        help="CA certificate of a tls/ router (default: $CAUSEWAY_BUS_TLS_ROOT_CA, else none)")


def resolve_target(args: argparse.Namespace, environ: Mapping[str, str] | None = None) -> Target:
    """The run named by ``add_target_arguments``' flags; ``OpsError`` when no run id can be found."""
    environ = os.environ if environ is None else environ
    found = read_run_dir(Path(args.run_dir)) if args.run_dir else Target("", "")
    connect = args.connect or found.connect or environ.get("CAUSEWAY_ZENOH_CONNECT") or LOOPBACK_ROUTER
    run_id = args.run_id or found.run_id or environ.get("CAUSEWAY_RUN_ID", "")
    if not run_id:
        raise OpsError("which run? give --run RUN_ID (and --connect ENDPOINT) or --run-dir runs/X")
    try:
        topics.alive(run_id)
    except ValueError as exc:
        raise OpsError(f"bad run id: {exc}") from None
    root_ca = getattr(args, "bus_tls_root_ca", None) or environ.get("CAUSEWAY_BUS_TLS_ROOT_CA", "")
    return Target(connect, run_id, _credentials(args, environ), root_ca)


def _credentials(args: argparse.Namespace, environ: Mapping[str, str]) -> Credentials | None:
    """The operator's credentials from the first of: --bus-credentials, the run dir, the environment."""
    path = getattr(args, "bus_credentials", None)
    if not path and args.run_dir and _run_uses_auth(Path(args.run_dir)):
        path = str(role_file(args.run_dir, "operator"))
    path = path or environ.get("CAUSEWAY_BUS_CREDENTIALS", "")
    if not path:
        return None
    try:
        return read_credentials(path)
    except ValueError as exc:
        raise OpsError(str(exc)) from None


def run_dir_config(run_dir: Path) -> dict:
    """The settings a local run was started with (its ``config.json``; empty if there is none)."""
    return _read_json(run_dir / "config.json") or {}


def _run_uses_auth(run_dir: Path) -> bool:
    """Whether the run was started with ``--bus-auth`` (a router without it refuses any credentials,
    so a run dir resumed without it must not lend its old ones)."""
    return bool(run_dir_config(run_dir).get("bus_auth"))


def read_run_dir(run_dir: Path) -> Target:
    """Router endpoint and run id of a local run directory (``OpsError`` if it is not one)."""
    config = _read_json(run_dir / "config.json")
    table = _read_json(run_dir / "processes.json")
    if config is None and table is None:
        raise OpsError(f"{run_dir} is not a run directory (no config.json or processes.json)")
    connect = (table or {}).get("router", "")
    if not connect and (config or {}).get("router_port"):
        connect = f"tcp/127.0.0.1:{config['router_port']}"
    return Target(connect, (config or {}).get("run_id", "") or run_dir.name)


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise OpsError(f"cannot read {path}: {exc}") from None


def open_bus(target: Target) -> ZenohTransport:
    """A Zenoh client session on the run's router; ``OpsError`` (exit 2) when the router does not answer."""
    import zenoh

    try:
        return ZenohTransport(target.connect, target.credentials, target.root_ca)
    except zenoh.ZError as exc:
        reason = str(exc).split("  at ")[0].strip()  # zenoh appends the Rust source location
        hint = "is the stack running?" + ("" if target.credentials else " does it need --bus-credentials?")
        raise OpsError(f"could not reach the Zenoh router at {target.connect} ({hint}): {reason}") from None


def check_scalable(service: str, count: int) -> None:
    """``OpsError`` unless ``service`` may be scaled to ``count``."""
    if service not in SCALABLE:
        raise OpsError(f"only {', '.join(SCALABLE)} can be scaled, not {service!r} "
                       f"(the learner and the evaluator own state: checkpoints, replay)")
    if count < 0:
        raise OpsError(f"cannot scale {service} to {count}")
