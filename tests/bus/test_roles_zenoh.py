"""The router with roles, over real Zenoh on loopback: who may connect, who may publish what.

A router started with a run's secrets (``services.bus.credentials``) and access control
(``services.bus.roles``) admits only its users, and drops a put its author's role does not allow.
"""
from __future__ import annotations

import contextlib
import functools
from pathlib import Path
from typing import Callable, Iterator

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

@contextlib.contextmanager
def serving(tmp_path: Path, roles: dict) -> Iterator[tuple[str, Callable[[str], ZenohTransport]]]:
    """A router on loopback with ``roles``' secrets (a password each, written under ``tmp_path``) and
    access control; yields its endpoint and ``client(user)``, a transport with that user's credentials.
    Everything opened is closed on the way out."""
    auth = write_run_secrets(tmp_path, new_passwords(tuple(roles)), access_control(roles))
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    session = start_router(endpoint, auth)
    opened: list[ZenohTransport] = []

    def client(user: str) -> ZenohTransport:
        opened.append(ZenohTransport(endpoint, read_credentials(role_file(tmp_path, user))))
        return opened[-1]

    try:
        yield endpoint, client
    finally:
        for transport in opened:
            transport.close()
        session.close()


@pytest.fixture
def router(tmp_path: Path):
    with serving(tmp_path, run_roles(RUN, "cdl")) as served:
        yield served


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
    # a key the forger may publish and the supervisor reads: its stats beat (the operator's: control/all)
    sync = topics.control(RUN, "all") if forger == "operator" else topics.stats(RUN, forger, "0")
    assert_forgery_refused(client, forger, key, owner, reader, sync)


def assert_forgery_refused(client, forger: str, key: str, owner: str, reader: str, sync: str) -> None:
    """``forger`` publishes on ``key`` then on ``sync`` (a key it may use, read by the supervisor) over
    the same link; once ``sync`` arrived, ``owner``'s message on ``key`` must reach ``reader`` and the
    forgery, which would have come before it, must not."""
    read, synced = [], []
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


@pytest.fixture
def instance_router(tmp_path: Path):
    """The local stack's router: a user per process (env-workers 0-2), each pinned to its own keys."""
    with serving(tmp_path, run_roles(RUN, "skild", workers=3)) as (endpoint, client):
        yield endpoint, client, tmp_path


INSTANCE_FORGERIES = [
    # (forger, key, its rightful publisher, a subscriber of the key): one process sending as another
    ("env-worker-0", topics.transitions(RUN, "w1"), "env-worker-1", "dynamics-learner"),
    ("env-worker-0", topics.stats(RUN, "env-worker", "1"), "env-worker-1", "supervisor"),
    ("env-worker-2", topics.skills(RUN, "w1"), "env-worker-1", "policy-learner"),
    ("env-worker-2", topics.stats(RUN, "dynamics-learner", "0"), "dynamics-learner", "supervisor"),
    ("dynamics-learner", topics.stats(RUN, "graph-evaluator", "0"), "graph-evaluator", "operator"),
]


@pytest.mark.parametrize("forger,key,owner,reader", INSTANCE_FORGERIES,
                         ids=[f"{f}->{k.split('/', 2)[2]}" for f, k, _, _ in INSTANCE_FORGERIES])
def test_a_process_cannot_publish_on_another_instances_keys(instance_router, forger: str, key: str, owner: str,
                                                           reader: str) -> None:
    """Worker A's credentials cannot publish on worker B's transitions, skills or stats keys, nor one service
    on another's beat; the forger's own beat, sent after the forgery on the same link, arrives, and so does
    the owner's message sent after that."""
    _, client, _ = instance_router
    instance = forger.rsplit("-", 1)[1] if forger.startswith("env-worker-") else "0"
    sync = topics.stats(RUN, forger.removesuffix(f"-{instance}") if forger.startswith("env-worker-") else forger,
                        instance)
    assert_forgery_refused(client, forger, key, owner, reader, sync)


def test_a_worker_keeps_its_own_keys_and_the_keys_all_workers_share(instance_router) -> None:
    """What pinning leaves each worker: its transitions and beat, its liveliness token, the env spec it
    serves and the policy it reads. No role-level env-worker user exists in such a run."""
    endpoint, client, secrets = instance_router
    assert not role_file(secrets, "env-worker").exists()
    learner, operator, policy = client("dynamics-learner"), client("operator"), client("policy-learner")
    batches, beats = [], []
    learner.subscribe(topics.transitions(RUN), lambda k, p: batches.append(k))
    operator.subscribe(topics.stats(RUN), lambda k, p: beats.append(k))
    served = policy.serve_latest(topics.weights(RUN, "policy"))
    served.set(b"policy")
    workers = [client(f"env-worker-{i}") for i in range(3)]
    workers[2].serve_latest(topics.env_spec(RUN)).set(b"spec")
    workers[0].declare_token(topics.alive(RUN, "env-worker", "2"))  # worker 2's: never declared
    for i, worker in enumerate(workers[:2]):
        worker.declare_token(topics.alive(RUN, "env-worker", str(i)))
        wait_for(lambda: worker.publish(topics.transitions(RUN, f"w{i}"), b"b") or topics.transitions(RUN, f"w{i}") in batches,
                 30, f"worker {i}'s batch")
        wait_for(lambda: worker.publish(topics.stats(RUN, "env-worker", str(i)), b"s", reliable=False)
                 or topics.stats(RUN, "env-worker", str(i)) in beats, 30, f"worker {i}'s beat")
        wait_for(lambda: worker.query(topics.weights(RUN, "policy")) == [(topics.weights(RUN, "policy"), b"policy")],
                 30, "the policy")
    wait_for(lambda: learner.query(topics.env_spec(RUN)) == [(topics.env_spec(RUN), b"spec")], 30, "the env spec")
    tokens = [topics.alive(RUN, "env-worker", str(i)) for i in range(3)]
    wait_for(lambda: sorted(operator.alive(topics.alive(RUN))) == tokens[:2], 30, "workers 0 and 1's own tokens")
    workers[2].declare_token(tokens[2])
    wait_for(lambda: sorted(operator.alive(topics.alive(RUN))) == tokens, 30, "worker 2's own token")
