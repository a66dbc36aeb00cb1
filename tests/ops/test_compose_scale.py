"""``causeway scale env-worker N --compose-project P`` against a recorded Docker Engine (``fake_docker``).

Checks the exact Engine API requests: scale-up clones a replica (image, command, environment,
labels with the next container numbers, restart policy, IPC namespace, volume, network alias
``env-worker``, no copied hostname) and starts the clones; scale-down stops (t=30) and removes the
highest-numbered replicas; other projects, other services and one-off containers are left alone.
"""
from __future__ import annotations

import io
import json
from typing import Iterator

import docker
import pytest

from services.cli import main as cli_main
from services.ops import compose_scale
from services.ops.target import OpsError
from tests.ops.fake_docker import FakeDockerEngine, fixture

PROJECT = "causeway"
RECORDED = fixture("containers/causeway-env-worker-1.json")


@pytest.fixture
def engine() -> Iterator[FakeDockerEngine]:
    with FakeDockerEngine() as running:
        yield running


@pytest.fixture
def client(engine: FakeDockerEngine) -> Iterator[docker.DockerClient]:
    c = docker.DockerClient(base_url=engine.base_url, version="1.43")
    yield c
    c.close()


def env_workers(engine: FakeDockerEngine, project: str = PROJECT) -> dict[str, dict]:
    """Name -> inspect document of the project's env-worker replicas the engine holds now."""
    return {c["Name"][1:]: c for c in engine.state.containers.values()
            if c["Config"]["Labels"].get(compose_scale.PROJECT) == project
            and c["Config"]["Labels"].get(compose_scale.SERVICE) == "env-worker"
            and c["Config"]["Labels"].get(compose_scale.ONEOFF) == "False"}


def test_scale_up_clones_the_replica_with_the_next_numbers(engine: FakeDockerEngine, client: docker.DockerClient) -> None:
    result = compose_scale.scale(client, PROJECT, "env-worker", 4)

    assert (result.before, result.after) == (2, 4)
    assert result.created == ["causeway-env-worker-3", "causeway-env-worker-4"]
    creates = engine.requests("POST", r"^/containers/create$")
    assert [r.query["name"] for r in creates] == ["causeway-env-worker-3", "causeway-env-worker-4"]
    for request, k in zip(creates, (3, 4)):
        body = request.body
        assert body["Image"] == "causeway:local"
        assert body["Cmd"] == ["python", "-m", "services.env_worker"]
        assert body["Env"] == RECORDED["Config"]["Env"] and "CAUSEWAY_WORKER_INDEX=-1" in body["Env"]
        assert body["Labels"] == {**RECORDED["Config"]["Labels"], "com.docker.compose.container-number": str(k)}
        assert body["Hostname"] == ""  # its own hostname, so its own worker index, seed and token
        assert body["User"] == "causeway" and body["WorkingDir"] == "/app"
        assert body["Healthcheck"] == RECORDED["Config"]["Healthcheck"]
        host = body["HostConfig"]
        assert host["RestartPolicy"] == {"Name": "unless-stopped", "MaximumRetryCount": 0}
        assert host["IpcMode"] == RECORDED["HostConfig"]["IpcMode"]
        assert host["Mounts"] == [{"Type": "volume", "Source": "causeway_causeway-data", "Target": "/data", "VolumeOptions": {}}]
        assert host["NetworkMode"] == "causeway_default"
        assert body["NetworkingConfig"] == {"EndpointsConfig": {"causeway_default": {"Aliases": [f"causeway-env-worker-{k}", "env-worker"]}}}
    new_ids = {engine.state.by_name(f"causeway-env-worker-{k}")[0]["Id"] for k in (3, 4)}
    started = {r.path.split("/")[2] for r in engine.requests("POST", r"/start$")}
    assert started == new_ids
    assert not engine.requests("POST", r"/stop$") and not engine.requests("DELETE")
    replicas = env_workers(engine)
    assert sorted(replicas) == [f"causeway-env-worker-{k}" for k in (1, 2, 3, 4)]
    assert all(c["State"]["Running"] for c in replicas.values())


def test_scale_down_stops_and_removes_the_highest_numbered(engine: FakeDockerEngine, client: docker.DockerClient) -> None:
    compose_scale.scale(client, PROJECT, "env-worker", 4)
    name_of = {c["Id"]: name for name, c in env_workers(engine).items()}
    result = compose_scale.scale(client, PROJECT, "env-worker", 1)

    assert (result.before, result.after) == (4, 1)
    assert result.removed == ["causeway-env-worker-4", "causeway-env-worker-3", "causeway-env-worker-2"]
    stops, deletes = engine.requests("POST", r"/stop$"), engine.requests("DELETE")
    assert all(r.query == {"t": "30"} for r in stops)
    assert [name_of[r.path.split("/")[2]] for r in stops] == result.removed
    assert [name_of[r.path.split("/")[2]] for r in deletes] == result.removed
    assert sorted(env_workers(engine)) == ["causeway-env-worker-1"]
    for untouched in ("causeway-dynamics-learner-1", "staging-env-worker-1", "causeway-env-worker-run-5a1b2c3d4e5f"):
        assert engine.state.by_name(untouched)


def test_scale_down_from_the_recorded_two_to_one(engine: FakeDockerEngine, client: docker.DockerClient) -> None:
    result = compose_scale.scale(client, PROJECT, "env-worker", 1)

    worker_2 = fixture("containers/causeway-env-worker-2.json")["Id"]
    assert result.removed == ["causeway-env-worker-2"]
    assert [(r.method, r.path, r.query) for r in engine.requests(pattern=worker_2 + r"(/stop)?$")
            if r.method != "GET"] == [("POST", f"/containers/{worker_2}/stop", {"t": "30"}),
                                      ("DELETE", f"/containers/{worker_2}", {"v": "False", "link": "False", "force": "False"})]
    assert not engine.requests("POST", r"^/containers/create$")


def test_only_the_project_and_service_labels_are_listed(engine: FakeDockerEngine, client: docker.DockerClient) -> None:
    found = compose_scale.replicas(client, PROJECT, "env-worker")

    assert [c.name for c in found] == ["causeway-env-worker-1", "causeway-env-worker-2"]
    listing = engine.requests("GET", r"^/containers/json$")[0]
    assert listing.query["all"] in ("1", "true")
    assert sorted(json.loads(listing.query["filters"])["label"]) == ["com.docker.compose.project=causeway",
                                                                      "com.docker.compose.service=env-worker"]


def test_the_same_numbers_are_not_reused_in_another_project(engine: FakeDockerEngine, client: docker.DockerClient) -> None:
    result = compose_scale.scale(client, "staging", "env-worker", 2)

    assert result.created == ["staging-env-worker-2"]
    body = engine.requests("POST", r"^/containers/create$")[0].body
    assert body["Labels"]["com.docker.compose.project"] == "staging"
    assert body["NetworkingConfig"]["EndpointsConfig"] == {"staging_default": {"Aliases": ["staging-env-worker-2", "env-worker"]}}


@pytest.mark.parametrize("service", ["dynamics-learner", "graph-evaluator", "router"])
def test_only_env_worker_is_scalable(engine: FakeDockerEngine, client: docker.DockerClient, service: str) -> None:
    with pytest.raises(OpsError, match="only env-worker can be scaled"):
        compose_scale.scale(client, PROJECT, service, 3)
    assert not engine.requests("POST")


def test_scaling_an_empty_project_is_a_clear_error(client: docker.DockerClient) -> None:
    with pytest.raises(OpsError, match="no env-worker container in compose project 'absent'"):
        compose_scale.scale(client, "absent", "env-worker", 2)


def test_scaling_to_zero_is_refused(client: docker.DockerClient) -> None:
    with pytest.raises(OpsError, match="no replica to clone"):
        compose_scale.scale(client, PROJECT, "env-worker", 0)


def test_extra_networks_are_connected_before_the_start() -> None:
    attrs = {**RECORDED, "NetworkSettings": {"Networks": {"causeway_default": {}, "causeway_metrics": {}}}}
    name, body, extra = compose_scale.clone_request(attrs, PROJECT, "env-worker", 7)

    assert name == "causeway-env-worker-7"
    assert list(body["NetworkingConfig"]["EndpointsConfig"]) == ["causeway_default"]
    assert extra == {"causeway_metrics": ["causeway-env-worker-7", "env-worker"]}


def test_compose_v1_names_are_followed() -> None:
    attrs = {**RECORDED, "Name": "/causeway_env-worker_1"}
    assert compose_scale.clone_request(attrs, PROJECT, "env-worker", 3)[0] == "causeway_env-worker_3"


def test_the_cli_scales_through_docker_host_with_version_negotiation(engine: FakeDockerEngine,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    code = cli_main(["scale", "env-worker", "3", "--compose-project", PROJECT, "--docker-host", engine.base_url])

    out = capsys.readouterr().out
    assert code == 0
    assert "causeway/env-worker: 2 -> 3 replicas (+causeway-env-worker-3)" in out
    assert engine.requests("GET", r"^/version$")
    assert len(engine.requests("POST", r"/start$")) == 1


def test_the_cli_rejects_other_services_before_calling_docker(engine: FakeDockerEngine,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    code = cli_main(["scale", "dynamics-learner", "2", "--compose-project", PROJECT, "--docker-host", engine.base_url])

    assert code == 2
    assert "only env-worker can be scaled" in capsys.readouterr().err
    assert not engine.requests()


def test_an_unreachable_engine_is_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    from services.bus.router import free_tcp_port

    code = cli_main(["scale", "env-worker", "2", "--compose-project", PROJECT,
                     "--docker-host", f"tcp://127.0.0.1:{free_tcp_port()}"])

    assert code == 2
    assert "could not reach the Docker engine" in capsys.readouterr().err


def test_an_engine_refusal_is_reported(engine: FakeDockerEngine) -> None:
    engine.state.images.clear()
    out = io.StringIO()
    with pytest.raises(OpsError, match="No such image: causeway:local") as raised:
        compose_scale.main(PROJECT, "env-worker", 3, engine.base_url, out)
    assert raised.value.exit_code == 1
