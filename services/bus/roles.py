"""Roles on the bus: what each kind of process may do on the router, and the router's access control.

One run, one set of roles. Each role is a Zenoh user (``transport/auth/usrpwd``) whose rules allow
exactly the key expressions its processes use, read from their ``service.py``, from
``services.runtime.shell`` (every service: its control topics, its liveliness token, its stats beats,
the EnvSpec query) and from ``services.ops`` (operators). Everything else is denied
(``default_permission: deny``), so an env-worker's credentials cannot publish weights or control, and
a client without credentials is refused when it opens its session.

Who publishes and who subscribes, per role (``<run>`` elided; ``<m>`` is the run's method):

| role | publishes | subscribes | serves (queryable) | queries | liveliness |
|---|---|---|---|---|---|
| env-worker | transitions/*, env/spec | weights/policy | env/spec | weights/policy | token |
| dynamics-learner | weights/<m> | transitions/*, graph/<m> | weights/<m> | env/spec | token |
| graph-evaluator | graph/<m>, local/<m> | transitions/*, weights/<m> | graph/<m>, local/<m> | weights/<m>, env/spec | token |
| intrinsic-reward | scored/* | transitions/*, weights/<m>, graph/<m> | | weights/<m>, graph/<m>, env/spec | token |
| policy-learner | weights/policy | transitions/* or scored/*, graph/<m> | weights/policy | env/spec | token |
| factor-extractor (runs with frames) | transitions/*, env/spec | frames/* | env/spec | env/frames | token |
| factor-extractor (FLAM's labels) | latent/* | frames/*, weights/<m> | | weights/<m>, env/spec | token |
| dashboard | | graph/*, local/*, stats/** of the watched runs | | graph/*, local/* | token |
| supervisor | control/all, control/env-worker | stats/**, graph/*, local/* | | | token |
| operator | control/* | stats/** | | | watches and queries alive/** |

In a run with frames (``--worker-publish-frames``) the env-worker publishes frames/* instead of
transitions/* and serves its spec on env/frames; the factor-extractor role exists only in such a run
or in a FLAM run with ``--label-latent-actions``, where the env-worker publishes frames/* beside
transitions/* and the extractor labels them (the second factor-extractor row).

Every service also publishes ``stats/<service>/*`` and subscribes to ``control/<service>`` and
``control/all``. How a capability becomes Zenoh ACL messages and flows (ingress: from the client to
the router; egress: from the router to the client), measured with eclipse-zenoh 1.10.2: a publisher
needs ingress ``put`` and egress ``declare_subscriber``; a subscriber ingress ``declare_subscriber``
and egress ``put``; a queryable ingress ``declare_queryable`` and ``reply`` and egress ``query``; a
querier ingress ``query`` and egress ``reply`` and ``declare_queryable``; a token holder ingress
``liveliness_token``; a liveliness watcher ingress ``declare_liveliness_subscriber`` and
``liveliness_query`` and egress ``liveliness_token``.

The publisher's egress ``declare_subscriber`` is not optional: a declared publisher filters on the
writer side, sending only while it knows of a matching subscriber, and learns of them from the
router's subscriber declarations. Without it, a client that declared a publisher on a key it may not
use stopped delivering on its *allowed* publishers too (every put after that declaration dropped),
and whether a first put got through depended on timing. Those declarations carry the subscriber's
key expression, so a publisher is allowed the subscriptions of every role that meet its keys (see
``_allowed_messages``); the querier's egress ``declare_queryable`` likewise.

In a run of SkiLD (``--method skild``) the env-worker also publishes skills/* and subscribes to and
queries weights/skild-policy, the graph-evaluator publishes induced/<m>/*, and the policy-learner
subscribes to skills/* and induced/<m>/* and serves weights/skild-policy (:data:`SKILL_KEYS`).

Identities per instance (``run_roles(..., workers=N)``, the local stack): one user per process, each
pinned to its own keys. Env-worker ``i`` is the user ``env-worker-i`` and may publish only
``transitions/w<i>`` (``frames/w<i>``, ``skills/w<i>``), ``stats/env-worker/<i>`` and the token
``alive/env-worker/<i>``, so no worker can send as another; every other service is its role's user,
pinned to instance ``0`` (``stats/<service>/0``, ``alive/<service>/0``). With ``workers=0`` (compose and
Kubernetes, where a service's replicas share one Secret) there is one ``env-worker`` user for every
replica and the pinning is per role only.

This module is pure: :func:`run_roles` declares, :func:`access_control` renders the router's JSON,
:func:`new_passwords` draws passwords; files are written by :mod:`services.bus.credentials`.
"""
from __future__ import annotations

import dataclasses
import secrets
from dataclasses import dataclass
from typing import Any

from proto import topics
from services.bus.memory import key_intersects

SERVICES = ("env-worker", "dynamics-learner", "graph-evaluator", "intrinsic-reward", "policy-learner",
            "dashboard")
"""Roles of the service processes; each service's processes share its role."""
ROLES = SERVICES + ("supervisor", "operator")
FRAMES_ROLE = "factor-extractor"
"""The role of a run with frames only (:func:`run_roles` with ``frames=True`` or ``latent=True``)."""
POLICY_MODEL = "policy"
"""The policy-learner's weights topic segment (``causal.rl.policy_weights.MODEL``)."""
SKILD_POLICY_MODEL = "skild-policy"
"""SkiLD's skill/task policies' weights topic segment (``causal.skild_policy.MODEL``)."""


@dataclass(frozen=True)
class Role:
    """The key expressions one role may use, by capability."""

    name: str
    publish: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    serve: tuple[str, ...] = ()
    """Queryables (``serve_latest``); a served value is also published, so these are in ``publish`` too."""
    query: tuple[str, ...] = ()
    tokens: tuple[str, ...] = ()
    """Liveliness tokens it declares."""
    watch: tuple[str, ...] = ()
    """Liveliness tokens it watches or queries."""


CAPABILITIES: dict[str, tuple[tuple[str, str], ...]] = {
    "publish": (("ingress", "put"), ("egress", "declare_subscriber")),
    "subscribe": (("ingress", "declare_subscriber"), ("egress", "put")),
    "serve": (("ingress", "declare_queryable"), ("egress", "query"), ("ingress", "reply")),
    "query": (("ingress", "query"), ("egress", "reply"), ("egress", "declare_queryable")),
    "tokens": (("ingress", "liveliness_token"),),
    "watch": (("ingress", "declare_liveliness_subscriber"), ("ingress", "liveliness_query"),
              ("egress", "liveliness_token")),
}
"""Capability -> the (flow, ACL message) pairs it needs on its keys (see the module notes)."""


def _service(run: str, name: str, *, publish: tuple[str, ...] = (), subscribe: tuple[str, ...] = (),
             serve: tuple[str, ...] = (), query: tuple[str, ...] = (), spec: bool = True) -> Role:
    """A service's role: what ``ServiceShell`` does for every service, plus its own keys."""
    return Role(name, publish=publish + serve + (topics.stats(run, name),),
                subscribe=subscribe + (topics.control(run, name), topics.control(run, "all")),
                serve=serve, query=query + ((topics.env_spec(run),) if spec else ()),
                tokens=(topics.alive(run, name),))


def run_roles(run: str, method: str, dashboard_run: str | None = None, frames: bool = False,
              workers: int = 0, latent: bool = False) -> dict[str, Role]:
    """Every role of run ``run`` whose learner, evaluator and reward use ``method``, by user name.

    ``dashboard_run`` is the run the dashboard shows (``*``: every run on the router; default ``run``).
    ``frames``: the env-workers publish frames, a factor-extractor turns them into transitions.
    ``latent``: the env-workers publish frames beside their transitions, a factor-extractor labels them
    with the learner's latent actions (FLAM, ``--label-latent-actions``).
    ``workers``: 0, one ``env-worker`` user shared by every replica; N > 0, the users ``env-worker-0`` ..
    ``env-worker-<N-1>``, each pinned to its own keys, and every other service pinned to instance 0
    (:func:`pinned`).
    """
    shown = run if dashboard_run is None else dashboard_run
    weights, policy = topics.weights(run, method), topics.weights(run, POLICY_MODEL)
    graph, local = topics.graph(run, method), topics.local(run, method)
    transitions, scored = topics.transitions(run), topics.scored(run)
    worker_publish, worker_spec = (topics.frames(run),), topics.frames_spec(run)
    if frames and latent:
        raise ValueError("frames (instead of transitions) and latent (frames beside them) exclude each other")
    if not frames:
        worker_publish, worker_spec = (transitions,) + ((topics.frames(run),) if latent else ()), topics.env_spec(run)
    extractor = (_service(run, FRAMES_ROLE, publish=(transitions,), subscribe=(topics.frames(run),),
                          serve=(topics.env_spec(run),), query=(topics.frames_spec(run),), spec=False),) if frames else ()
    if latent:
        extractor = (_service(run, FRAMES_ROLE, publish=(topics.latent_actions(run),),
                              subscribe=(topics.frames(run), weights), query=(weights,)),)
    roles = extractor + (
        _service(run, "env-worker", publish=worker_publish, subscribe=(policy,), serve=(worker_spec,),
                 query=(policy,), spec=False),
        _service(run, "dynamics-learner", subscribe=(transitions, graph), serve=(weights,)),
        _service(run, "graph-evaluator", subscribe=(transitions, weights), serve=(graph, local), query=(weights,)),
        _service(run, "intrinsic-reward", publish=(scored,), subscribe=(transitions, weights, graph),
                 query=(weights, graph)),
        _service(run, "policy-learner", subscribe=(transitions, scored, graph), serve=(policy,)),
        _service(run, "dashboard", spec=False,
                 subscribe=(topics.graph(shown), topics.local(shown), topics.stats(shown)),
                 query=(topics.graph(shown), topics.local(shown))),
        Role("supervisor", publish=(topics.control(run, "all"), topics.control(run, "env-worker")),
             subscribe=(topics.stats(run), topics.graph(run), topics.local(run),
                        topics.control(run, "supervisor"), topics.control(run, "all")),
             tokens=(topics.alive(run, "supervisor", "0"),)),
        Role("operator", publish=(topics.control(run),), subscribe=(topics.stats(run),), watch=(topics.alive(run),)),
    )
    roles = tuple(_with_skills(role, run, method) for role in roles)
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    if workers:
        roles = tuple(inst for role in roles for inst in
                      ([pinned(role, run, i) for i in range(workers)] if role.name == "env-worker" else [pinned(role, run)]))
    return {role.name: role for role in roles}


def instance_user(service: str, index: int) -> str:
    """The bus user of env-worker ``index`` in a run with identities per instance (``env-worker-3``);
    also the supervisor's name for that process and the stem of its credentials file."""
    return f"{service}-{index}"


def pinned(role: Role, run: str, index: int | None = None) -> Role:
    """``role`` narrowed to one instance: its stats beats and liveliness token under its instance id
    (``index``, or 0 for a service of one process); an env-worker's also its own ``transitions``,
    ``frames`` and ``skills`` keys (worker id ``w<index>``, as ``EnvWorkerCore.worker_id``), and the user
    :func:`instance_user`. Keys the role shares with its peers (``env/spec``, the policy) stay as they are."""
    instance = str(index or 0)
    narrow = {topics.stats(run, role.name): topics.stats(run, role.name, instance),
              topics.alive(run, role.name): topics.alive(run, role.name, instance)}
    name = role.name
    if index is not None:
        worker = f"w{index}"
        narrow.update({topics.transitions(run): topics.transitions(run, worker),
                       topics.frames(run): topics.frames(run, worker), topics.skills(run): topics.skills(run, worker)})
        name = instance_user(role.name, index)

    def own(keys: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(narrow.get(key, key) for key in keys)

    return dataclasses.replace(role, name=name, publish=own(role.publish), serve=own(role.serve), tokens=own(role.tokens))


SKILL_KEYS = {
    "env-worker": {"publish": ("skills",), "subscribe": ("skild-policy",), "query": ("skild-policy",)},
    "graph-evaluator": {"publish": ("induced",)},
    "policy-learner": {"subscribe": ("skills", "induced"), "serve": ("skild-policy",)},
}
"""SkiLD's extra keys per role (a ``skild`` run only): names resolved by :func:`_skill_key`."""


def _skill_key(run: str, method: str, name: str) -> str:
    return {"skills": topics.skills(run), "induced": topics.induced(run, method),
            "skild-policy": topics.weights(run, SKILD_POLICY_MODEL)}[name]


def _with_skills(role: Role, run: str, method: str) -> Role:
    """``role`` with SkiLD's keys added in a run of method ``skild`` (a served key is published too)."""
    extra = SKILL_KEYS.get(role.name) if method == "skild" else None
    if not extra:
        return role
    keys = {cap: tuple(_skill_key(run, method, n) for n in names) for cap, names in extra.items()}
    publish = keys.get("publish", ()) + keys.get("serve", ())
    return dataclasses.replace(role, publish=role.publish + publish,
                               subscribe=role.subscribe + keys.get("subscribe", ()),
                               serve=role.serve + keys.get("serve", ()), query=role.query + keys.get("query", ()))


def _allowed_messages(role: Role, roles: dict[str, Role]) -> dict[tuple[str, str], set[str]]:
    """(flow, ACL message) -> the key expressions ``role`` may use it on.

    A subscription is declared to a publisher with the *subscriber's* key expression (``stats/*/*``
    to a worker publishing ``stats/env-worker/0``), and a router allows an egress declaration only
    inside the rule's keys; so a publisher is also allowed every subscription of any role that meets
    its keys, and a querier every queryable that meets its queries. Without that a subscriber that
    came after the publisher (``causeway status`` reading stats beats) never received anything."""
    allowed: dict[tuple[str, str], set[str]] = {}
    for capability, pairs in CAPABILITIES.items():
        for pair in pairs:
            allowed.setdefault(pair, set()).update(getattr(role, capability))
    for mine, theirs, message in (("publish", "subscribe", "declare_subscriber"), ("query", "serve", "declare_queryable")):
        allowed[("egress", message)].update(
            key for other in roles.values() for key in getattr(other, theirs)
            if any(key_intersects(key, own) for own in getattr(role, mine)))
    return {pair: keys for pair, keys in allowed.items() if keys}


def access_control(roles: dict[str, Role]) -> dict[str, Any]:
    """The router's ``access_control`` configuration: deny by default, each role's capabilities allowed
    for the user of the same name. A rule several users need (the env-workers' shared keys) is written
    once and named by each of their policies."""
    rules: list[dict[str, Any]] = []
    policies = []
    ids_of: dict[tuple[str, str, tuple[str, ...]], str] = {}
    for role in roles.values():
        ids = []
        for (flow, message), keys in sorted(_allowed_messages(role, roles).items()):
            rule = (flow, message, tuple(sorted(keys)))
            if rule not in ids_of:
                ids_of[rule] = f"{role.name}-{flow}-{message}"
                rules.append({"id": ids_of[rule], "permission": "allow", "flows": [flow], "messages": [message],
                              "key_exprs": list(rule[2])})
            ids.append(ids_of[rule])
        policies.append({"id": role.name, "rules": ids, "subjects": [role.name]})
    subjects = [{"id": role.name, "usernames": [role.name]} for role in roles.values()]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def new_passwords(roles: tuple[str, ...] = ROLES) -> dict[str, str]:
    """A fresh random password per role (``secrets``: 32 bytes, URL-safe, so never a ``:``)."""
    return {role: secrets.token_urlsafe(32) for role in roles}
