"""``causeway bus-secrets``: a run's bus credentials and router configuration for a stack without a
supervisor (compose, Kubernetes), which therefore cannot draw them itself.

    causeway bus-secrets --run compose --method cdl --out deploy [--router-config deploy/zenoh/router.json5]
                         [--users-file /run/secrets/causeway-router-users] [--dashboard-run '*'] [--file-mode 644]

Writes into ``<out>/secrets`` (mode 700; files 600) what a local run keeps in ``<run_dir>/secrets``: one
``<role>.credentials`` per role, the router's ``router-users`` and ``access-control.json``, and
``router.json5``: the ``--router-config`` file with user/password authentication (its dictionary
read from ``--users-file``, where the router's container mounts ``router-users``) and the access
control added. Mount each service's ``<role>.credentials`` as a secret and point
``CAUSEWAY_BUS_CREDENTIALS`` at it. Fresh passwords every time: restart the whole stack after.

``--file-mode 644`` is for Compose: outside Swarm a compose secret is a bind mount of the file with
its host owner and mode (``uid``/``gid``/``mode`` are ignored), and the containers run as other users
(the image's ``causeway``, uid 10001), so a 600 file of the host user cannot be read in them. The
directory stays 700: on the host only its owner reaches the files; each container sees only the
files mounted into it.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

from proto import topics
from services.bus.credentials import SECRETS_DIR, write_run_secrets
from services.bus.roles import access_control, new_passwords, run_roles

ROUTER_FILE = "router.json5"


def router_file(base: Path, users_file: str, acl: dict) -> str:
    """``base`` (a Zenoh router configuration) with authentication and access control, as JSON."""
    import zenoh

    config = zenoh.Config.from_file(str(base))
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(users_file))
    config.insert_json5("access_control", json.dumps(acl))
    return json.dumps(json.loads(str(config)), indent=1) + "\n"


def _file_mode(text: str) -> int:
    """An octal file mode that gives no one but the owner write access (600 or 644, say)."""
    mode = int(text, 8)
    if not 0o400 <= mode <= 0o644 or mode & 0o133:
        raise argparse.ArgumentTypeError(f"{text}: expected an octal mode from 400 to 644 without write or execute "
                                         "bits for others (600: owner only; 644: readable in containers)")
    return mode


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="causeway bus-secrets", description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="run id of the stack (compose: compose)")
    parser.add_argument("--method", default="cdl", help="the stack's --method (names its weights and graph topics)")
    parser.add_argument("--out", required=True, help="directory whose secrets/ to write into (created, mode 700)")
    parser.add_argument("--router-config", default="deploy/zenoh/router.json5", help="the router configuration to extend")
    parser.add_argument("--users-file", default="/run/secrets/causeway-router-users",
                        help="where the router will read router-users (its path inside the router's container)")
    parser.add_argument("--dashboard-run", default="*", help="runs the dashboard may read (*: every run on the router)")
    parser.add_argument("--file-mode", default="600", type=_file_mode,
                        help="mode of the files, octal (644 for compose secrets, which keep the host mode; "
                             "the directory stays 700)")
    args = parser.parse_args(argv)
    try:
        topics.alive(args.run)
        roles = run_roles(args.run, args.method, dashboard_run=args.dashboard_run)
    except ValueError as exc:
        parser.error(str(exc))
    acl = access_control(roles)
    auth = write_run_secrets(args.out, new_passwords(tuple(roles)), acl)
    target = Path(args.out) / SECRETS_DIR / ROUTER_FILE
    target.touch(0o600)
    target.write_text(router_file(Path(args.router_config), args.users_file, acl))
    for written in target.parent.iterdir():
        written.chmod(args.file_mode)
    print(f"causeway bus-secrets: {len(roles)} roles of run {args.run} in {target.parent} "
          f"(router: {target}, users: {auth.users_file})", file=sys.stderr)
    return 0
