"""``causeway bus-secrets``: a run's bus credentials and router configuration for a stack without a
supervisor (compose, Kubernetes), which therefore cannot draw them itself.

    causeway bus-secrets --run compose --method cdl --out deploy [--extractor none|frames|latent]
                         [--router-config deploy/zenoh/router.json5]
                         [--users-file /run/secrets/causeway-router-users] [--dashboard-run '*'] [--file-mode 644]
                         [--listen ENDPOINT ...] [--tls-name NAME ...] [--tls-dir DIR] [--mesh-user NAME ...]
                         [--join tls/HOST:PORT ... --join-credentials FILE --join-ca FILE]

Writes into ``<out>/secrets`` (mode 700; files 600) what a local run keeps in ``<run_dir>/secrets``: one
``<role>.credentials`` per role, the router's ``router-users`` and ``access-control.json``, and
``router.json5``: the ``--router-config`` file with user/password authentication (its dictionary
read from ``--users-file``, where the router's container mounts ``router-users``) and the access
control added. Mount each service's ``<role>.credentials`` as a secret and point
``CAUSEWAY_BUS_CREDENTIALS`` at it. Fresh passwords every time: restart the whole stack after.

``--extractor``: a stack with a factor-extractor (deploy/compose.frames.yaml, deploy/compose.labels.yaml)
adds its role and changes the env-workers': ``frames``, the workers publish frames instead of
transitions and the extractor publishes slot transitions (``causeway run --worker-publish-frames
true``); ``latent``, the workers publish frames beside their transitions and the extractor labels
them with the learner's latent actions (``causeway run --label-latent-actions true``). Without it (``none``)
``factor-extractor.credentials`` is written all the same, for a user the router does not admit (in
neither ``router-users`` nor the access control): a kustomize base generates every Secret from a file
that must exist (deploy/k8s generates ``bus-factor-extractor`` for its frames and labels overlays),
while a stack without an extractor has no such role.

``--file-mode 644`` is for Compose: outside Swarm a compose secret is a bind mount of the file with
its host owner and mode (``uid``/``gid``/``mode`` are ignored), and the containers run as other users
(the image's ``causeway``, uid 10001), so a 600 file of the host user cannot be read in them. The
directory stays 700: on the host only its owner reaches the files; each container sees only the
files mounted into it.

Links that leave a host (docs/bus-roles.md, "TLS"): ``--tls-name`` (once per name the router is reached
by: a Service's DNS names, a host's address) also makes a CA and a router certificate for those names
(:mod:`services.ops.bus_tls`): ``bus-ca.pem`` (what clients trust: mount it beside their credentials,
``CAUSEWAY_BUS_TLS_ROOT_CA``), ``router-tls.pem``/``router-tls.key`` (the router's, read from
``--tls-dir``), ``bus-ca.key`` (mode 600 whatever ``--file-mode`` says; it only signs, mount it
nowhere). ``--listen`` replaces the configuration's listen endpoints (``tls/[::]:7447``).

Meshed routers: on the router that is joined, ``--mesh-user NAME`` adds a user for a router of another
host (its ``NAME.credentials`` goes to that host); the access control lets that user carry the run's
keys both ways and nothing else. On the joining router, ``--join tls/HOST:PORT`` with that file
(``--join-credentials``) and the first router's ``bus-ca.pem`` (``--join-ca``) makes it connect over
TLS as that user and let the routed traffic in from a router certified by that CA
(``causeway-router``); its own clients still need its own roles.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path, PurePosixPath
from typing import Sequence

from proto import topics
from services.bus.credentials import SECRETS_DIR, read_credentials, write_role_credentials, write_run_secrets
from services.bus.roles import FRAMES_ROLE, ROLES, access_control, new_passwords, run_roles
from services.bus.router import ROUTER_COMMON_NAME, with_meshed_routers
from services.ops.bus_tls import CA_CERTIFICATE, CA_KEY, write_tls

EXTRACTORS = ("none", "frames", "latent")
"""``--extractor``: which factor-extractor the stack runs, if any (:func:`services.bus.roles.run_roles`)."""
ROUTER_FILE = "router.json5"
ROUTER_ROOTS = "router-roots.pem"
"""The CAs the router verifies other routers against when it connects to them (its own, the joined one's)."""


def router_file(base: Path, users_file: str, acl: dict, settings: dict[str, object] | None = None) -> str:
    """``base`` (a Zenoh router configuration) with authentication, access control and ``settings``
    (Zenoh configuration paths to values), as JSON."""
    import zenoh

    config = zenoh.Config.from_file(str(base))
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(users_file))
    config.insert_json5("access_control", json.dumps(acl))
    for path, value in (settings or {}).items():
        config.insert_json5(path, json.dumps(value))
    return json.dumps(json.loads(str(config)), indent=1) + "\n"


def _listen_endpoints(base: Path, listen: Sequence[str]) -> list[str]:
    import zenoh

    return list(listen) or json.loads(zenoh.Config.from_file(str(base)).get_json("listen/endpoints"))


def _file_mode(text: str) -> int:
    """An octal file mode that gives no one but the owner write access (600 or 644, say)."""
    mode = int(text, 8)
    if not 0o400 <= mode <= 0o644 or mode & 0o133:
        raise argparse.ArgumentTypeError(f"{text}: expected an octal mode from 400 to 644 without write or execute "
                                         "bits for others (600: owner only; 644: readable in containers)")
    return mode


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="causeway bus-secrets", description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="run id of the stack (compose: compose)")
    parser.add_argument("--method", default="cdl", help="the stack's --method (names its weights and graph topics)")
    parser.add_argument("--out", required=True, help="directory whose secrets/ to write into (created, mode 700)")
    parser.add_argument("--extractor", choices=EXTRACTORS, default="none",
                        help="the stack's factor-extractor: none; frames (workers publish frames, the extractor slot "
                             "transitions); latent (frames beside transitions, the extractor latent-action labels)")
    parser.add_argument("--router-config", default="deploy/zenoh/router.json5", help="the router configuration to extend")
    parser.add_argument("--users-file", default="/run/secrets/causeway-router-users",
                        help="where the router will read router-users (its path inside the router's container)")
    parser.add_argument("--dashboard-run", default="*", help="runs the dashboard may read (*: every run on the router)")
    parser.add_argument("--file-mode", default="600", type=_file_mode,
                        help="mode of the files, octal (644 for compose secrets, which keep the host mode; "
                             "the directory stays 700)")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                        help="the router's listen endpoints, replacing the configuration's (e.g. tls/[::]:7447)")
    parser.add_argument("--tls-name", action="append", default=[], metavar="NAME",
                        help="a DNS name or IP address the router is reached by: make a CA and a router certificate "
                             "for all of them (needs a tls/ listen endpoint)")
    parser.add_argument("--tls-dir", default="", help="where the router reads its certificate files (default: the "
                                                      "directory of --users-file)")
    parser.add_argument("--mesh-user", action="append", default=[], metavar="NAME",
                        help="a user for a router of another host that joins this one (writes NAME.credentials)")
    parser.add_argument("--join", action="append", default=[], metavar="tls/HOST:PORT",
                        help="connect this router to another host's router (over TLS)")
    parser.add_argument("--join-credentials", default="", help="the joined router's NAME.credentials for this router")
    parser.add_argument("--join-ca", default="", help="the joined router's bus-ca.pem")
    return parser


def _check(parser: argparse.ArgumentParser, args: argparse.Namespace, listen: list[str]) -> None:
    """Refuse a combination that would give a router that cannot start or a link in clear."""
    tls_listen = [e for e in listen if e.startswith("tls/")]
    if tls_listen and not args.tls_name:
        parser.error(f"the router listens on {tls_listen[0]} but has no certificate: add --tls-name NAME "
                     "(each name clients reach it by)")
    if args.tls_name and not tls_listen:
        parser.error("--tls-name makes a certificate for a tls/ endpoint, but the router listens on none "
                     f"({', '.join(listen) or 'no endpoint'}): add --listen tls/[::]:7447")
    for user in args.mesh_user:
        if user in ROLES or not user or ":" in user:
            parser.error(f"--mesh-user {user!r}: a router's own user, not a role ({', '.join(ROLES)}) and without ':'")
    if args.join and not all(e.startswith("tls/") for e in args.join):
        parser.error("--join: a link between routers leaves a host; use tls/HOST:PORT")
    if bool(args.join) != bool(args.join_credentials) or bool(args.join) != bool(args.join_ca):
        parser.error("--join needs --join-credentials and --join-ca (the joined router's NAME.credentials and "
                     "bus-ca.pem), and they need --join")


def _tls_settings(args: argparse.Namespace, directory: Path) -> dict[str, object]:
    """Certificates (and the joined router's CA) into ``directory``; the router configuration that reads them."""
    where = PurePosixPath(args.tls_dir or str(PurePosixPath(args.users_file).parent))
    settings: dict[str, object] = {}
    roots = []
    if args.tls_name:
        files = write_tls(directory, args.tls_name)
        settings["transport/link/tls/listen_certificate"] = str(where / files.certificate.name)
        settings["transport/link/tls/listen_private_key"] = str(where / files.private_key.name)
        roots.append(files.ca_certificate.read_text())
    if args.join:
        roots.append(Path(args.join_ca).read_text())
        joining = read_credentials(args.join_credentials)
        settings.update({"connect/endpoints": list(args.join), "transport/auth/usrpwd/user": joining.user,
                         "transport/auth/usrpwd/password": joining.password})
    if roots:
        (directory / ROUTER_ROOTS).touch(0o600)
        (directory / ROUTER_ROOTS).write_text("".join(roots))
        settings["transport/link/tls/root_ca_certificate"] = str(where / ROUTER_ROOTS)
    return settings


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        listen = _listen_endpoints(Path(args.router_config), args.listen)
    except Exception as exc:  # zenoh.ZError: a missing or malformed --router-config
        parser.error(f"--router-config {args.router_config}: {exc}")
    _check(parser, args, listen)
    try:
        topics.alive(args.run)
        roles = run_roles(args.run, args.method, dashboard_run=args.dashboard_run, frames=args.extractor == "frames",
                          latent=args.extractor == "latent")
        acl = with_meshed_routers(access_control(roles), args.run, usernames=args.mesh_user,
                                  cert_common_names=[ROUTER_COMMON_NAME] if args.join else [])
        passwords = new_passwords(tuple(roles) + tuple(args.mesh_user))
        auth = write_run_secrets(args.out, passwords, acl)
        if FRAMES_ROLE not in roles:  # a file for kustomize's generator, for a user no router admits
            write_role_credentials(args.out, FRAMES_ROLE, new_passwords((FRAMES_ROLE,))[FRAMES_ROLE])
        target = Path(args.out) / SECRETS_DIR / ROUTER_FILE
        settings = _tls_settings(args, target.parent)
        if args.listen:
            settings["listen/endpoints"] = list(args.listen)
    except (ValueError, OSError) as exc:
        parser.error(str(exc))
    target.touch(0o600)
    target.write_text(router_file(Path(args.router_config), args.users_file, acl, settings))
    for written in target.parent.iterdir():
        written.chmod(0o600 if written.name == CA_KEY else args.file_mode)
    tls = f", TLS: {CA_CERTIFICATE} for clients" if args.tls_name else ""
    print(f"causeway bus-secrets: {len(roles)} roles of run {args.run} in {target.parent} "
          f"(router: {target}, users: {auth.users_file}{tls})", file=sys.stderr)
    return 0
