"""Roles on the bus (services.bus.roles): the router's access control allows every key each service and
operator command uses, and nothing a role does not own.

The coverage tests record every bus call the real service code makes (the in-process stack with
every service, and the operator commands on an in-memory bus) and check each against its role; the
router then enforcing those rules is tested over real Zenoh in ``test_roles_zenoh.py``.
"""
from __future__ import annotations

import threading
import time
from collections import defaultdict

import pytest
import torch

from proto import topics
from services.bus.memory import InMemoryBus, InMemoryTransport
from causal.rl.policy_weights import MODEL
from services.bus.roles import CAPABILITIES, POLICY_MODEL, ROLES, Role, access_control, new_passwords, run_roles
from services.ops.control import alive_now, send
from services.ops.observe import RunObserver
from services.runtime.config import build_config
from services.supervisor import inprocess
from services.supervisor.config import RunConfig
from services.supervisor.wiring import learning_services

RUN = "acl"


def includes(pattern: str, key_expr: str) -> bool:
    """Whether every key matching ``key_expr`` matches ``pattern`` (``*``: one chunk, ``**``: any)."""
    p, k = pattern.split("/"), key_expr.split("/")
    if p and p[-1] == "**":
        return len(k) >= len(p) - 1 and all(includes_chunk(a, b) for a, b in zip(p[:-1], k))
    return len(p) == len(k) and all(includes_chunk(a, b) for a, b in zip(p, k))


def includes_chunk(pattern: str, chunk: str) -> bool:
    return pattern == chunk or (pattern == "*" and chunk != "**")


def allowed(role: Role, capability: str, key_expr: str) -> bool:
    return any(includes(pattern, key_expr) for pattern in getattr(role, capability))


class RecordingTransport(InMemoryTransport):
    """An in-memory endpoint that records (capability, key) of every call, under its thread's role."""

    calls: dict[str, set[tuple[str, str]]] = defaultdict(set)

    def __init__(self, bus: InMemoryBus | None = None, role: str | None = None) -> None:
        super().__init__(bus)
        name = role or threading.current_thread().name
        self.role = "env-worker" if name.startswith("env-worker") else name

    def _record(self, capability: str, key: str) -> None:
        self.calls[self.role].add((capability, key))

    def publish(self, key, payload, *, reliable=True):
        self._record("publish", key)
        return super().publish(key, payload, reliable=reliable)

    def subscribe(self, key_expr, callback):
        self._record("subscribe", key_expr)
        return super().subscribe(key_expr, callback)

    def serve_latest(self, key):
        self._record("serve", key)
        return super().serve_latest(key)

    def query(self, key_expr, timeout=1.0):
        self._record("query", key_expr)
        return super().query(key_expr, timeout)

    def declare_token(self, key):
        self._record("tokens", key)
        return super().declare_token(key)

    def watch_liveliness(self, key_expr, callback):
        self._record("watch", key_expr)
        return super().watch_liveliness(key_expr, callback)

    def alive(self, key_expr, timeout=1.0):
        self._record("watch", key_expr)
        return super().alive(key_expr, timeout)


def denied(calls: dict[str, set[tuple[str, str]]], roles: dict[str, Role]) -> list[str]:
    return sorted(f"{role}: {capability} {key}" for role, made in calls.items()
                  for capability, key in made if not allowed(roles[role], capability, key))


def test_access_control_denies_by_default_and_gives_each_role_its_user() -> None:
    roles = run_roles(RUN, "cdl")
    acl = access_control(roles)
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert [s["usernames"] for s in acl["subjects"]] == [[r] for r in ROLES]
    ids = [rule["id"] for rule in acl["rules"]]
    assert len(ids) == len(set(ids))
    assert {i for p in acl["policies"] for i in p["rules"]} == set(ids)
    for rule in acl["rules"]:
        assert rule["permission"] == "allow" and len(rule["flows"]) == 1 and rule["messages"] and rule["key_exprs"]
        assert all(flow in ("ingress", "egress") for flow in rule["flows"])
    assert {m for pairs in CAPABILITIES.values() for _, m in pairs} <= {
        "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
        "declare_liveliness_subscriber", "liveliness_query"}


def test_each_role_publishes_only_its_own_keys() -> None:
    roles = run_roles(RUN, "cdl")
    control, weights = topics.control(RUN, "x"), topics.weights(RUN, "cdl")
    publishers = {key: sorted(r.name for r in roles.values() if allowed(r, "publish", key))
                  for key in (control, weights, topics.weights(RUN, "policy"), topics.graph(RUN, "cdl"),
                              topics.transitions(RUN, "w0"), topics.scored(RUN, "w0"), topics.control(RUN, "all"))}
    assert publishers == {control: ["operator"], weights: ["dynamics-learner"],
                          topics.weights(RUN, "policy"): ["policy-learner"], topics.graph(RUN, "cdl"): ["graph-evaluator"],
                          topics.transitions(RUN, "w0"): ["env-worker"], topics.scored(RUN, "w0"): ["intrinsic-reward"],
                          topics.control(RUN, "all"): ["operator", "supervisor"]}
    assert not any(allowed(r, c, topics.alive("other")) for r in roles.values() for c in ("subscribe", "watch"))


def test_the_policy_weights_segment_is_the_policy_learners() -> None:
    assert POLICY_MODEL == MODEL


def test_passwords_are_fresh_random_and_colon_free() -> None:
    first, second = new_passwords(), new_passwords()
    assert set(first) == set(ROLES)
    assert all(len(p) >= 40 and ":" not in p for p in first.values())
    assert not set(first.values()) & set(second.values())


def test_operator_commands_stay_within_the_operator_role() -> None:
    bus = InMemoryBus()
    RecordingTransport.calls.clear()
    operator = RecordingTransport(bus, role="operator")
    send(operator, RUN, "all", "stop")
    send(operator, RUN, "supervisor", "scale", "env-worker=2")
    alive_now(operator, RUN, "env-worker")
    with RunObserver(operator, RUN):
        pass
    assert RecordingTransport.calls["operator"] and not denied(RecordingTransport.calls, run_roles(RUN, "cdl"))


@pytest.fixture(scope="module")
def stack_calls(tmp_path_factory, request):
    """Every bus call of every service of a run with all of them (policy, intrinsic reward, dashboard)."""
    torch.set_num_threads(1)
    cfg = build_config(RunConfig, graph="chain", num_objects=3, run_dir=str(tmp_path_factory.mktemp("run")),
                       run_id=RUN, cdl_feature_hidden=16, cdl_feature_dim=16, cdl_predictor_hidden=16,
                       cdl_batch_size=32, evaluator_min_interval_s=0.5, learner_publish_every_s=0.5,
                       worker_max_steps_per_second=2000, progress=False, workers=1, collector="ppo",
                       intrinsic="preddiff")
    overrides = {"dynamics-learner": {"warmup_steps": 200}, "graph-evaluator": {"min_heldout": 100},
                 "policy-learner": {"rollout_batches": 1, "minibatch_size": 64, "epochs": 1, "hidden": 16},
                 "dashboard": {"http_port": 0}}
    RecordingTransport.calls.clear()
    patch = pytest.MonkeyPatch()
    patch.setattr(inprocess, "InMemoryTransport", RecordingTransport)
    request.addfinalizer(patch.undo)
    stack = inprocess.InProcessStack(cfg, services=learning_services(inprocess.resolve(cfg)) + ("dashboard",),
                                     config_overrides=overrides)
    stack.start()
    deadline = time.monotonic() + 300
    wanted = {("serve", topics.graph(RUN, "cdl")), ("publish", topics.graph(RUN, "cdl"))}
    while time.monotonic() < deadline and not wanted <= RecordingTransport.calls["graph-evaluator"]:
        time.sleep(1.0)
    time.sleep(3.0)
    stack.stop(timeout=120)
    return {role: calls for role, calls in RecordingTransport.calls.items() if role in ROLES}  # not the test's own


def test_every_service_of_the_stack_uses_only_what_its_role_allows(stack_calls) -> None:
    roles = run_roles(RUN, "cdl")
    assert set(stack_calls) >= set(roles) - {"supervisor", "operator"}
    assert ("publish", topics.graph(RUN, "cdl")) in stack_calls["graph-evaluator"]
    assert not denied(stack_calls, roles)


def test_every_call_of_the_stack_fits_the_identities_per_instance_too(stack_calls) -> None:
    """The local stack's users (one per process): its one worker is env-worker-0, every other service
    instance 0; every call the stack made is still allowed."""
    roles = run_roles(RUN, "cdl", workers=2)
    calls = {("env-worker-0" if role == "env-worker" else role): made for role, made in stack_calls.items()}
    assert not denied(calls, roles)


def test_identities_per_instance_pin_each_process_to_its_own_keys() -> None:
    roles = run_roles(RUN, "skild", workers=3)
    assert "env-worker" not in roles and {f"env-worker-{i}" for i in range(3)} <= set(roles)
    owners = {key: sorted(r.name for r in roles.values() if allowed(r, "publish", key))
              for key in (topics.transitions(RUN, "w1"), topics.skills(RUN, "w1"), topics.stats(RUN, "env-worker", "1"),
                          topics.stats(RUN, "dynamics-learner", "0"), topics.stats(RUN, "dynamics-learner", "1"),
                          topics.transitions(RUN, "w3"), topics.env_spec(RUN))}
    assert owners == {topics.transitions(RUN, "w1"): ["env-worker-1"], topics.skills(RUN, "w1"): ["env-worker-1"],
                      topics.stats(RUN, "env-worker", "1"): ["env-worker-1"],
                      topics.stats(RUN, "dynamics-learner", "0"): ["dynamics-learner"],
                      topics.stats(RUN, "dynamics-learner", "1"): [], topics.transitions(RUN, "w3"): [],
                      topics.env_spec(RUN): ["env-worker-0", "env-worker-1", "env-worker-2"]}
    tokens = [r.name for r in roles.values() if allowed(r, "tokens", topics.alive(RUN, "env-worker", "2"))]
    assert tokens == ["env-worker-2"]
    frames = run_roles(RUN, "cdl", frames=True, workers=2)
    assert [r.name for r in frames.values() if allowed(r, "publish", topics.frames(RUN, "w1"))] == ["env-worker-1"]
    roles = run_roles(RUN, "cdl", workers=3)
    acl = access_control(roles)
    assert {u for s in acl["subjects"] for u in s["usernames"]} == set(roles)
    shared = [rule for rule in acl["rules"] if rule["key_exprs"] == [topics.weights(RUN, "policy")]
              and rule["flows"] == ["ingress"] and rule["messages"] == ["query"]]
    assert len(shared) == 1  # one rule, named by every worker's policy
    assert sum(shared[0]["id"] in p["rules"] for p in acl["policies"]) == 3
    with pytest.raises(ValueError):
        run_roles(RUN, "cdl", workers=-1)
