"""The ``causeway`` command: ``causeway run [flags]`` starts the embedded default stack.

Every flag of ``causeway run`` is a field of ``services.supervisor.config.RunConfig``
(``causeway run --help`` lists them with their defaults). The operator commands act on a running
stack (``causeway <command> --help`` for each; ``services/ops/``):

    causeway status     (--run RUN [--connect E] | --run-dir runs/X) [--json] [--listen-s 2.5]
    causeway scale env-worker N (--run ... | --run-dir ... | --compose-project P [--docker-host URL])
    causeway stop       (--run RUN [--connect E] | --run-dir runs/X)
    causeway checkpoint (--run RUN [--connect E] | --run-dir runs/X)

and two act on finished runs: ``causeway final-graph --run-dir runs/X`` (the final model's graph on
all held-out data into the run's summary; ``services.supervisor.final_graph``), and ``causeway compare
RUN...`` puts finished runs side by side by the results contract's scores (``services.supervisor.compare``).
``causeway bus-secrets --run RUN --out DIR`` writes a stack's bus credentials and router
configuration where no supervisor draws them (compose, Kubernetes; ``services.ops.bus_secrets``).
"""
from __future__ import annotations

import importlib
import logging
import sys
from typing import Callable

from services.runtime.config import USAGE_EXIT, parse_config

Command = Callable[[list[str]], int]


def _run(argv: list[str]) -> int:
    """``causeway run``: every flag and file is checked before anything starts (exit 2 with the reason)."""
    from services.supervisor.analysis import print_summary
    from services.supervisor.config import RunConfig
    from services.supervisor.supervisor import Supervisor

    cfg = parse_config(RunConfig, argv, prog="causeway run")
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    try:
        supervisor = Supervisor(cfg)
        supervisor.preflight()
    except ValueError as exc:
        print(f"causeway run: error: {exc}", file=sys.stderr)
        return USAGE_EXIT
    print(f"causeway: run {supervisor.cfg.run_id} in {supervisor.run_dir} "
          f"(router {supervisor.connect}, logs in {supervisor.run_dir / 'logs'})", file=sys.stderr)
    if supervisor.dashboard_url:
        print(f"causeway: live graph at {supervisor.dashboard_url}", file=sys.stderr)
    content = supervisor.run()
    print_summary(content)
    print(f"causeway: wrote {supervisor.run_dir / 'summary.json'}", file=sys.stderr)
    if supervisor.failure:
        print(f"causeway: error: {supervisor.failure}", file=sys.stderr)
        return 1
    return 0


def _operator(name: str, module: str, function: str) -> Command:
    """``causeway <name>``: ``services.ops.<module>.<function>(argv)``, imported only when used.

    An ``OpsError`` becomes one line on stderr and its exit status (2: unreachable or invalid,
    1: sent but not confirmed in time)."""

    def command(argv: list[str]) -> int:
        from services.ops.target import OpsError

        try:
            return getattr(importlib.import_module(f"services.ops.{module}"), function)(argv)
        except OpsError as exc:
            print(f"causeway {name}: {exc}", file=sys.stderr)
            return exc.exit_code

    return command


COMMANDS: dict[str, Command] = {
    "run": _run,
    "status": _operator("status", "status", "main"),
    "scale": _operator("scale", "control", "scale_main"),
    "stop": _operator("stop", "control", "stop_main"),
    "checkpoint": _operator("checkpoint", "control", "checkpoint_main"),
    "final-graph": lambda argv: importlib.import_module("services.supervisor.final_graph").main(argv),
    "bus-secrets": lambda argv: importlib.import_module("services.ops.bus_secrets").main(argv),
    "compare": lambda argv: importlib.import_module("services.supervisor.compare").main(argv),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        print(f"usage: causeway {{{','.join(COMMANDS)}}} [--help] [flags]", file=sys.stderr)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    return COMMANDS[argv[0]](argv[1:])


if __name__ == "__main__":
    sys.exit(main())
