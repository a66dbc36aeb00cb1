"""The ``causeway`` command: ``causeway run [flags]`` starts the embedded default stack.

Every flag of ``causeway run`` is a field of ``services.supervisor.config.RunConfig``
(``causeway run --help`` lists them with their defaults).
"""
from __future__ import annotations

import logging
import sys

from services.runtime.config import parse_config


def _run(argv: list[str]) -> int:
    from services.supervisor.config import RunConfig
    from services.supervisor.supervisor import Supervisor, print_summary

    cfg = parse_config(RunConfig, argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    supervisor = Supervisor(cfg)
    print(f"causeway: run {supervisor.cfg.run_id} in {supervisor.run_dir} "
          f"(router {supervisor.connect}, logs in {supervisor.run_dir / 'logs'})", file=sys.stderr)
    content = supervisor.run()
    print_summary(content)
    print(f"causeway: wrote {supervisor.run_dir / 'summary.json'}", file=sys.stderr)
    return 0


COMMANDS = {"run": _run}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        print(f"usage: causeway {{{','.join(COMMANDS)}}} [--help] [flags]", file=sys.stderr)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    return COMMANDS[argv[0]](argv[1:])


if __name__ == "__main__":
    sys.exit(main())
