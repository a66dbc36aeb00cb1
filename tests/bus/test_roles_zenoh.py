"""The router with roles, over real Zenoh on loopback: who may connect, who may publish what.

A router started with a run's secrets (``services.bus.credentials``) and access control
(``services.bus.roles``) admits only its users, and drops a put its author's role does not allow.
"""
from __future__ import annotations

import functools
from pathlib import Path

import pytest
import zenoh

from proto import topics
from services.bus.credentials import Credentials, read_credentials, role_file, write_run_secrets
from services.bus.roles import access_control, new_passwords, run_roles
from services.bus.router import free_tcp_port, start_router
from services.bus.zenoh_transport import ZenohTransport
from tests import waiting

pytestmark = pytest.mark.integration
RUN = "acl"


wait_for = functools.partial(waiting.wait_for, interval=0.1)

@pytest.fixture
def router(tmp_path: Path):
    auth = write_run_secrets(tmp_path, new_passwords(), access_control(run_roles(RUN, "cdl")))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    session = start_router(endpoint, auth)
    opened: list[ZenohTransport] = []

    def client(role: str) -> ZenohTransport:
        opened.append(ZenohTransport(endpoint, read_credentials(role_file(tmp_path, role))))
        return opened[-1]

    yield endpoint, client
    for transport in opened:
        transport.close()
    session.close()


def test_secrets_are_private_to_their_owner(tmp_path: Path) -> None:
    write_run_secrets(tmp_path, new_passwords(), access_control(run_roles(RUN, "cdl")))
    assert (tmp_path / "secrets").stat().st_mode & 0o777 == 0o700
    files = list((tmp_path / "secrets").iterdir())
    assert len(files) == 10 and all(f.stat().st_mode & 0o777 == 0o600 for f in files)
    assert "password=<hidden>" in repr(read_credentials(role_file(tmp_path, "operator")))


@pytest.mark.parametrize("credentials", [None, Credentials("env-worker", "wrong"), Credentials("nobody", "x")],
                         ids=["anonymous", "wrong-password", "unknown-user"])
def test_clients_without_valid_credentials_are_refused(router, credentials) -> None:
    endpoint, _ = router
    with pytest.raises(zenoh.ZError):
        ZenohTransport(endpoint, credentials).close()


def test_an_env_worker_cannot_publish_control_or_weights_and_the_operator_can(router) -> None:
    """Each forgery is followed, on the same links, by a message its subscriber must get: had the router
    let the forgery through, it would have arrived first (one link, one subscriber, in order)."""
    _, client = router
    control, weights, batches = [], [], []
    client("supervisor").subscribe(topics.control(RUN, "all"), lambda k, p: control.append(p))
    client("graph-evaluator").subscribe(topics.weights(RUN, "cdl"), lambda k, p: weights.append(p))
    learner = client("dynamics-learner")
    learner.subscribe(topics.transitions(RUN), lambda k, p: batches.append(p))
    worker, operator = client("env-worker"), client("operator")
    wait_for(lambda: worker.publish(topics.transitions(RUN, "w0"), b"batch") or batches, 30, "a transition batch")
    worker.publish(topics.control(RUN, "all"), b"forged stop")
    worker.publish(topics.weights(RUN, "cdl"), b"forged weights")
    worker.publish(topics.transitions(RUN, "w0"), b"last")
    wait_for(lambda: batches[-1] == b"last", 30, "the worker's batch after its forgeries")
    operator.publish(topics.control(RUN, "all"), b"stop")
    learner.publish(topics.weights(RUN, "cdl"), b"weights")
    wait_for(lambda: control and weights, 30, "the operator's stop and the learner's weights")
    assert control == [b"stop"] and weights == [b"weights"]


def test_queries_and_liveliness_follow_the_roles(router) -> None:
    _, client = router
    worker, learner, operator = client("env-worker"), client("dynamics-learner"), client("operator")
    worker.serve_latest(topics.env_spec(RUN)).set(b"spec")
    worker.declare_token(topics.alive(RUN, "env-worker", "0"))
    weights = learner.serve_latest(topics.weights(RUN, "cdl"))
    weights.set(b"w")
    wait_for(lambda: learner.query(topics.env_spec(RUN)) == [(topics.env_spec(RUN), b"spec")], 30, "the env spec")
    assert worker.query(topics.weights(RUN, "cdl")) == []  # an env-worker may not read the dynamics model
    wait_for(lambda: operator.alive(topics.alive(RUN)) == [topics.alive(RUN, "env-worker", "0")], 30, "the token")


def test_a_subscriber_that_comes_after_the_publisher_receives(router) -> None:
    """``causeway status`` subscribes to ``stats/*/*`` long after the services declared their publishers:
    the router must be allowed to tell each publisher of that subscription (see ``roles._allowed_messages``)."""
    _, client = router
    worker, beat = client("env-worker"), topics.stats(RUN, "env-worker", "0")
    worker.publish(beat, b"before anyone listens")
    beats: list[bytes] = []
    client("operator").subscribe(topics.stats(RUN), lambda k, p: beats.append(p))
    wait_for(lambda: worker.publish(beat, b"beat", reliable=False) or beats, 30, "a beat")


FORGERIES = [
    # (forger, key, its rightful publisher, a subscriber of the key): issue 20's forged messages
    ("env-worker", topics.control(RUN, "all"), "operator", "supervisor"),  # a forged stop
    ("dashboard", topics.control(RUN, "all"), "supervisor", "dynamics-learner"),
    ("env-worker", topics.control(RUN, "supervisor"), "operator", "supervisor"),  # a forged scale request
    ("env-worker", topics.weights(RUN, "cdl"), "dynamics-learner", "graph-evaluator"),  # forged weights
    ("graph-evaluator", topics.weights(RUN, "cdl"), "dynamics-learner", "intrinsic-reward"),
    ("intrinsic-reward", topics.weights(RUN, "policy"), "policy-learner", "env-worker"),
    ("env-worker", topics.graph(RUN, "cdl"), "graph-evaluator", "supervisor"),  # a forged report
    ("dynamics-learner", topics.graph(RUN, "cdl"), "graph-evaluator", "policy-learner"),
    ("dynamics-learner", topics.transitions(RUN, "w0"), "env-worker", "graph-evaluator"),  # forged batches
    ("operator", topics.scored(RUN, "w0"), "intrinsic-reward", "policy-learner"),
]


@pytest.mark.parametrize("forger,key,owner,reader", FORGERIES, ids=[f"{f}->{k.split('/', 2)[2]}" for f, k, _, _ in FORGERIES])
def test_a_forgery_by_the_wrong_role_never_arrives(router, forger: str, key: str, owner: str, reader: str) -> None:
    """The forger's own beat, sent after the forgery on the same link, is seen first; the owner's message
    is sent after that, so a forgery the router let through would reach the reader before it."""
    _, client = router
    read, synced = [], []
    # a key the forger may publish and the supervisor reads: its stats beat (the operator's: control/all)
    sync = topics.control(RUN, "all") if forger == "operator" else topics.stats(RUN, forger, "0")
    client(reader).subscribe(key, lambda k, p: read.append(p))
    client("supervisor").subscribe(sync, lambda k, p: synced.append(p))
    forging, owning = client(forger), client(owner)
    wait_for(lambda: owning.publish(key, b"warm-up") or read, 30, "the owner's message")
    forging.publish(key, b"forged")
    forging.publish(sync, b"sync")
    wait_for(lambda: b"sync" in synced, 30, "the forger's next message")
    owning.publish(key, b"owner")
    wait_for(lambda: b"owner" in read, 30, "the owner's message")
    assert b"forged" not in read, read
