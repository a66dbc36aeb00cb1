"""The Zenoh router in-process, and the client configuration every service uses to reach it.

Topology: one router, every service a *client* of it (a star). Clients were chosen over peers
because clients listen on no port (nothing to allocate per service in tests or to expose in
compose), every query and liveliness question has one authority (the router), and a dead service
is noticed by the router the moment its TCP link drops. The price is one extra hop: on loopback,
64 KB BLOCK messages ran at about 1.7 GB/s client-router-client against 2.7 GB/s peer-to-peer with
gossip, measured with eclipse-zenoh 1.10.2 on this machine; the bus is not the bottleneck.

Facts about eclipse-zenoh 1.10.2 that shaped this module (measured here):

- ``zenoh.open`` of a router takes 500 ms by default: ``scouting/delay`` defaults to 500 ms even
  with multicast off. ``scouting/delay: 0`` makes it ~2 ms.
- A client whose router is not listening fails at once with ``ZError("Unable to connect to any
  of ...")`` rather than waiting, hence ``wait_for_router``'s retry loop.
- Clients reconnect on their own when the router comes back (about 1 s after a router restart on
  the same endpoint) and redeclare their subscribers and liveliness tokens; liveliness watchers
  see every token go (False) and come back (True).
- A client does not listen by default, but ``listen/endpoints`` is set empty to make it explicit.
"""
from __future__ import annotations

import json
import socket
import time
from typing import Any, Sequence

import zenoh

from proto import topics
from services.bus.credentials import Credentials, RouterAuth, RouterTls

LOOPBACK_ROUTER = "tcp/127.0.0.1:7447"
"""The embedded default: the local supervisor's router."""

ROUTER_COMMON_NAME = "causeway-router"
"""The common name of every router certificate ``causeway bus-secrets --tls-name`` makes; a router that
joins another trusts the far side of its link by it (and by the CA that signed it)."""

ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query")
"""Every message kind Zenoh 1.10's access control filters."""


def with_meshed_routers(acl: dict[str, Any], run: str, usernames: Sequence[str] = (),
                        cert_common_names: Sequence[str] = ()) -> dict[str, Any]:
    """``acl`` (a router's ``access_control``) that also lets the run's traffic cross links to other routers.

    Routers meshed across hosts carry every role's messages, so the link between two of them is allowed
    every message kind, both ways, on the run's keys (``causeway/<run>/**``) and nothing else. Who is a
    router: on the router that is joined, the user the joining router authenticates as (``usernames``);
    on the joining router, the router it connected to, by its certificate's common name
    (``cert_common_names``; Zenoh's ``usrpwd`` authenticates only the side that opens the link). Each
    router still applies its own roles to its own clients: a router is trusted to enforce them."""
    subjects = ([{"id": "meshed-router-users", "usernames": list(usernames)}] if usernames else []) + \
        ([{"id": "meshed-router-certificates", "cert_common_names": list(cert_common_names)}] if cert_common_names
         else [])  # two subjects: one subject's properties must all match
    if not subjects:
        return acl
    topics.alive(run)  # a valid run id
    rule = {"id": "meshed-routers", "permission": "allow", "flows": ["ingress", "egress"],
            "messages": list(ALL_MESSAGES), "key_exprs": [f"{topics.ROOT}/{run}/**"]}
    policy = {"id": "meshed-routers", "rules": ["meshed-routers"], "subjects": [s["id"] for s in subjects]}
    return {**acl, "rules": [*acl["rules"], rule], "subjects": [*acl["subjects"], *subjects],
            "policies": [*acl["policies"], policy]}


def router_config(listen: str = LOOPBACK_ROUTER, auth: RouterAuth | None = None,
                  tls: RouterTls | None = None) -> zenoh.Config:
    """A router listening on ``listen`` only, multicast scouting off, gossip scouting on.

    With ``auth``: only users of its dictionary are admitted (a client without credentials, or with a
    wrong password, fails to open its session) and each may do only what its role allows
    (:mod:`services.bus.roles`); whatever a role does not allow is dropped by the router. With ``tls``
    (and a ``tls/HOST:PORT`` ``listen``): the router's certificate and key, so links are encrypted
    and clients verify the router (``client_config``'s ``root_ca``)."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("router"))
    config.insert_json5("listen/endpoints", json.dumps([listen]))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/delay", "0")
    if auth is not None:
        config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(auth.users_file)))
        config.insert_json5("access_control", json.dumps(auth.access_control))
    if tls is not None:
        config.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(tls.certificate)))
        config.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(tls.private_key)))
    return config


def start_router(listen: str = LOOPBACK_ROUTER, auth: RouterAuth | None = None,
                 tls: RouterTls | None = None) -> zenoh.Session:
    """Open a Python session in router mode on ``listen``; close the session to stop the router."""
    return zenoh.open(router_config(listen, auth, tls))


def client_config(connect: str, credentials: Credentials | None = None, root_ca: str = "") -> zenoh.Config:
    """A client of the router at ``connect``: no listening, no multicast scouting; with
    ``credentials``, it authenticates as that user; with ``root_ca`` (a PEM file), it verifies a
    ``tls/`` router's certificate against that CA (a TLS router is refused without it)."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([connect]))
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    if credentials is not None:
        config.insert_json5("transport/auth/usrpwd/user", json.dumps(credentials.user))
        config.insert_json5("transport/auth/usrpwd/password", json.dumps(credentials.password))
    if root_ca:
        config.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(root_ca))
    return config


def wait_for_router(connect: str, timeout: float = 10.0, interval: float = 0.05,
                    credentials: Credentials | None = None) -> None:
    """Return once a client session to ``connect`` opens; raise ``TimeoutError`` after ``timeout`` s.

    A router that requires credentials refuses a session without them: pass ``credentials`` there."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            zenoh.open(_one_attempt_config(connect, deadline, credentials)).close()
            return
        except zenoh.ZError as error:
            if time.monotonic() + interval > deadline:
                raise TimeoutError(f"no Zenoh router at {connect} after {timeout} s") from error
        time.sleep(interval)


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (the kernel's pick), for tests."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def _one_attempt_config(connect: str, deadline: float, credentials: Credentials | None = None) -> zenoh.Config:
    """``client_config`` whose connection attempt gives up by ``deadline`` (unreachable hosts hang)."""
    config = client_config(connect, credentials)
    remaining_ms = max(1, int((deadline - time.monotonic()) * 1000))
    config.insert_json5("connect/timeout_ms", str(min(remaining_ms, 1000)))
    return config
