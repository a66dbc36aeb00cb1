"""Scale the env-worker replicas of a running Docker Compose project through the Engine API.

    causeway scale env-worker N --compose-project P [--docker-host URL]

Compose marks its containers with labels: ``com.docker.compose.project``, ``.service`` and
``.container-number``. Scaling up clones an existing replica, the way ``docker compose up --scale``
would create one: same image, command, environment, labels (with the next container number), host
config (restart policy, volumes, IPC namespace) and networks, with the aliases ``<name>`` and
``env-worker`` so Docker's DNS (and Prometheus' ``dns_sd_configs``) finds it, named
``<project>-env-worker-<k>``. The clone's hostname is left to Docker (its own container id),
because a worker with ``CAUSEWAY_WORKER_INDEX=-1`` derives its index, seed and liveliness key
from the hostname. Scaling down stops (30 s for a clean checkpoint-and-exit) and removes the
highest-numbered replicas. Only env-worker is scalable: the learner and the evaluator own state.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any, Sequence, TextIO

import docker
import docker.errors
from docker.models.containers import Container

from services.ops.target import OpsError, check_scalable

PROJECT = "com.docker.compose.project"
SERVICE = "com.docker.compose.service"
NUMBER = "com.docker.compose.container-number"
ONEOFF = "com.docker.compose.oneoff"
STOP_TIMEOUT_S = 30


@dataclass(frozen=True)
class ScaleResult:
    """What a scale changed: replica counts and container names."""

    before: int
    after: int
    created: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)


def docker_client(docker_host: str | None = None) -> docker.DockerClient:
    """``--docker-host`` if given, else the environment (``DOCKER_HOST`` or the local socket)."""
    try:
        client = docker.DockerClient(base_url=docker_host) if docker_host else docker.from_env()
        client.api.ping()
        return client
    except docker.errors.DockerException as exc:
        raise OpsError(f"could not reach the Docker engine at {docker_host or '$DOCKER_HOST / the local socket'}: {exc}") from None


def number(container: Container) -> int:
    return int(container.labels.get(NUMBER, "0") or 0)


def replicas(client: docker.DockerClient, project: str, service: str) -> list[Container]:
    """The service's containers in the project (stopped ones too, one-off ``run`` ones not), by number."""
    found = client.containers.list(all=True, filters={"label": [f"{PROJECT}={project}", f"{SERVICE}={service}"]})
    return sorted((c for c in found if c.labels.get(ONEOFF, "False") != "True"), key=number)


def template(existing: Sequence[Container], project: str, service: str) -> Container:
    """The replica to clone: the lowest-numbered running one, else the lowest-numbered."""
    if not existing:
        raise OpsError(f"no {service} container in compose project {project!r} to clone "
                       f"(start the stack first: make up)")
    running = [c for c in existing if c.attrs.get("State", {}).get("Running")]
    return (running or list(existing))[0]


def replica_name(source_name: str, project: str, service: str, k: int) -> str:
    """``<project>-<service>-<k>`` (Compose v2), or ``<project>_<service>_<k>`` beside v1-named replicas."""
    separator = "_" if source_name.lstrip("/").startswith(f"{project}_{service}_") else "-"
    return separator.join((project, service, str(k)))


def clone_request(attrs: dict[str, Any], project: str, service: str, k: int) -> tuple[str, dict[str, Any], dict[str, list[str]]]:
    """(name, create body, {extra network: aliases}) of replica ``k`` cloned from inspected ``attrs``.

    The Engine API (< 1.44) attaches one network at create time; any others are connected after.
    """
    name = replica_name(attrs.get("Name", ""), project, service, k)
    body = copy.deepcopy(attrs["Config"])
    body["Hostname"] = ""
    body.pop("MacAddress", None)
    body["Labels"] = {**(body.get("Labels") or {}), NUMBER: str(k)}
    body["HostConfig"] = copy.deepcopy(attrs["HostConfig"])
    networks = list((attrs.get("NetworkSettings") or {}).get("Networks") or {})
    mode = body["HostConfig"].get("NetworkMode", "")
    primary = mode if mode in networks else (networks[0] if networks else "")
    aliases = [name, service]
    if primary:
        body["NetworkingConfig"] = {"EndpointsConfig": {primary: {"Aliases": aliases}}}
    return name, body, {n: aliases for n in networks if n != primary}


def add_replica(client: docker.DockerClient, source: Container, project: str, service: str, k: int) -> str:
    """Create, attach and start replica ``k``; returns its name."""
    name, body, extra = clone_request(source.attrs, project, service, k)
    created = client.api.create_container_from_config(body, name=name)
    for network, aliases in extra.items():
        client.api.connect_container_to_network(created["Id"], network, aliases=aliases)
    client.api.start(created["Id"])
    return name


def remove_replica(container: Container) -> str:
    """Stop (SIGTERM, then SIGKILL after 30 s) and remove; returns the name."""
    container.stop(timeout=STOP_TIMEOUT_S)
    container.remove()
    return container.name


def scale(client: docker.DockerClient, project: str, service: str, count: int) -> ScaleResult:
    """Make ``count`` replicas of ``service`` in ``project``: clone the first, or remove the last."""
    check_scalable(service, count)
    if count < 1:
        raise OpsError("scaling to 0 leaves no replica to clone later; use: docker compose up -d --scale env-worker=0")
    existing = replicas(client, project, service)
    if count > len(existing):
        source, first = template(existing, project, service), max(map(number, existing), default=0) + 1
        created = [add_replica(client, source, project, service, k) for k in range(first, first + count - len(existing))]
        return ScaleResult(len(existing), count, created=created)
    removed = [remove_replica(c) for c in reversed(existing[count:])]
    return ScaleResult(len(existing), count, removed=removed)


def main(project: str, service: str, count: int, docker_host: str | None, out: TextIO) -> int:
    """``causeway scale SERVICE N --compose-project P``; prints what changed."""
    check_scalable(service, count)
    client = docker_client(docker_host)
    try:
        result = scale(client, project, service, count)
    except docker.errors.APIError as exc:
        raise OpsError(f"the Docker engine refused: {exc.explanation or exc}", exit_code=1) from None
    finally:
        client.close()
    changed = [f"+{n}" for n in result.created] + [f"-{n}" for n in result.removed]
    out.write(f"{project}/{service}: {result.before} -> {result.after} replicas"
              f"{' (' + ', '.join(changed) + ')' if changed else ' (no change)'}\n")
    return 0
