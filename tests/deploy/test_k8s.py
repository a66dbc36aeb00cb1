"""deploy/k8s: rendered offline by ``kubectl kustomize`` and validated against the Kubernetes API
schemas that ``kubernetes-validate`` bundles (strict: unknown fields are errors); then the shape
issue 21 asks for (router Deployment + Service, env-workers scaled by an HPA, learners as
StatefulSets with volume claims, scrape annotations, services reaching only the router), settings
every service's config parser accepts, and roles on the bus: a Secret per role from the files
``causeway bus-secrets`` writes (kustomize ``secretGenerator``), each mounted by its role's pods only,
the router running the generated configuration; and TLS: the router listens on ``tls/`` only with a
certificate for the Service's names from its Secret, every service connects with ``tls/`` and has the
CA that signed it mounted beside its credentials, the CA's key in no Secret. All of it holds for the
base and the overlays, each rendered with the secrets its documented bus-secrets command makes:
``deploy/k8s-policy`` (compose's ``policy`` profile: the policy-learner, the intrinsic-reward, env-workers
that follow the policy), ``deploy/k8s-frames`` and ``deploy/k8s-labels`` (compose's frames and labels
overrides: the factor-extractor)."""
from __future__ import annotations

import base64
import copy
import json
import re
import shlex
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from services.bus.credentials import read_credentials
from services.bus.roles import access_control, run_roles
from services.cli import main as cli_main
from services.dashboard.config import DashboardConfig
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.env_worker.config import EnvWorkerConfig
from services.factor_extractor.config import FactorExtractorConfig
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.policy_learner.config import PolicyLearnerConfig
from services.runtime.config import parse_config, settings_parser
from tests.deploy import REPO, require_tool

kubernetes_validate = pytest.importorskip("kubernetes_validate", reason="pip install -e '.[test]' installs it")
yaml = pytest.importorskip("yaml")

integration = pytest.mark.integration
KUBERNETES_VERSIONS = ("1.30.0", kubernetes_validate.latest_version())
CONFIGS = {"env-worker": EnvWorkerConfig, "dynamics-learner": DynamicsLearnerConfig,
           "graph-evaluator": GraphEvaluatorConfig, "dashboard": DashboardConfig,
           "policy-learner": PolicyLearnerConfig, "intrinsic-reward": IntrinsicRewardConfig,
           "factor-extractor": FactorExtractorConfig}
POLICY = {"policy-learner", "intrinsic-reward"}
"""compose.yaml's ``policy`` profile: only the overlay runs them."""
OVERLAY = "k8s-policy"
EXTRACTOR = "factor-extractor"
EXTRACTOR_OVERLAYS = {"k8s-frames": "compose.frames.yaml", "k8s-labels": "compose.labels.yaml"}
"""deploy/<directory> -> the compose override (deploy/<file>) it is the equivalent of; only they run the extractor."""
BASE = set(CONFIGS) - POLICY - {EXTRACTOR}
RENDERS = {"k8s": BASE, OVERLAY: BASE | POLICY, **{overlay: BASE | {EXTRACTOR} for overlay in EXTRACTOR_OVERLAYS}}
"""deploy/<directory> -> the services its render runs."""
STATEFUL = {"dynamics-learner", "graph-evaluator", "policy-learner", "factor-extractor"}
"""The services that checkpoint to their run dir (the intrinsic-reward saves nothing: a Deployment)."""
ROUTER = {"app.kubernetes.io/part-of": "causeway", "app.kubernetes.io/component": "router"}
KUBE_DNS = {"k8s-app": "kube-dns"}
PROMETHEUS = {"app.kubernetes.io/name": "prometheus"}
BUS_SECRETS = ("causeway bus-secrets --run k8s --method cdl --out deploy/k8s --users-file /etc/zenoh/router-users "
               "--listen 'tls/[::]:7447' --tls-name router --tls-name router.causeway.svc "
               "--tls-name router.causeway.svc.cluster.local --tls-name localhost")
"""The command kustomization.yaml documents; it writes the files its secretGenerator reads."""
EXTRACTOR_SECRETS = {"k8s-frames": f"{BUS_SECRETS} --extractor frames",
                     "k8s-labels": f"{BUS_SECRETS.replace('--method cdl', '--method flam')} --extractor latent"}
"""The command each extractor overlay's kustomization.yaml documents: the same files, with the extractor's role."""
SECRETS = {directory: EXTRACTOR_SECRETS.get(directory, BUS_SECRETS) for directory in RENDERS}
"""deploy/<directory> -> the bus-secrets command it is applied after."""
SETTINGS_CHANGES = {"k8s-labels": {"CAUSEWAY_METHOD": "flam"}}
"""deploy/<overlay> -> what it changes in causeway-settings (compose: CAUSEWAY_METHOD=flam make up)."""
CREDENTIALS = "/run/secrets/causeway/credentials"
ROOT_CA = "/run/secrets/causeway/ca.pem"
SERVICE_NAMES = {"router", "router.causeway.svc", "router.causeway.svc.cluster.local"}
"""What a pod reaches the router by: the Service's names in namespace causeway."""


def _kustomize(directory: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([require_tool("kubectl"), "kustomize", str(directory)], capture_output=True, text=True,
                          timeout=60)


def _copy_without_secrets(target: Path) -> Path:
    """deploy/k8s as a fresh clone has it (no generated secrets/), the overlays beside it."""
    for overlay in set(RENDERS) - {"k8s"}:
        shutil.copytree(REPO / "deploy" / overlay, target.parent / overlay)
    return Path(shutil.copytree(REPO / "deploy" / "k8s", target, ignore=shutil.ignore_patterns("secrets")))


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Copies of deploy/k8s (the overlays beside each), one per documented command, with the secrets that
    command generates: command -> the copy."""
    copies = {}
    for command in dict.fromkeys(SECRETS.values()):
        k8s = _copy_without_secrets(tmp_path_factory.mktemp("deploy") / "k8s")
        args = shlex.split(command)[1:]
        args[args.index("--out") + 1] = str(k8s)
        assert cli_main(args + ["--router-config", str(REPO / "deploy" / "zenoh" / "router.json5")]) == 0
        copies[command] = k8s
    return copies


def _rendered(directory: Path) -> list[dict[str, Any]]:
    """``kubectl kustomize directory``: every object, namespace applied."""
    result = _kustomize(directory)
    assert result.returncode == 0, result.stderr
    return [doc for doc in yaml.safe_load_all(result.stdout) if doc]


@pytest.fixture(scope="module")
def renders(generated: dict[str, Path]) -> dict[str, list[dict[str, Any]]]:
    """``kubectl kustomize deploy/<directory>`` for each of RENDERS, with the secrets its command generates."""
    return {directory: _rendered(generated[SECRETS[directory]].parent / directory) for directory in RENDERS}


@pytest.fixture(scope="module", params=sorted(RENDERS))
def render(request: pytest.FixtureRequest) -> str:
    """Which directory's render a test checks: the base, then the overlay."""
    return request.param


@pytest.fixture(scope="module")
def manifests(renders: dict[str, list[dict[str, Any]]], render: str) -> list[dict[str, Any]]:
    return renders[render]


def _find(manifests: list[dict[str, Any]], kind: str, name: str) -> dict[str, Any]:
    found = [m for m in manifests if m["kind"] == kind and m["metadata"]["name"] == name]
    assert len(found) == 1, f"{kind}/{name}: {len(found)} found"
    return found[0]


def _containers(workload: dict[str, Any]) -> list[dict[str, Any]]:
    return workload["spec"]["template"]["spec"]["containers"]


def _secret(manifests: list[dict[str, Any]], name: str) -> dict[str, Any]:
    """The generated Secret ``name`` (kustomize appends a hash of its content to the name)."""
    found = [m for m in manifests if m["kind"] == "Secret" and m["metadata"]["name"].rsplit("-", 1)[0] == name]
    assert len(found) == 1, f"Secret/{name}: {len(found)} found"
    return found[0]


def _secret_file(secret: dict[str, Any], key: str, target: Path) -> Path:
    target.write_bytes(base64.b64decode(secret["data"][key]))
    return target


def _mounted_secrets(workload: dict[str, Any]) -> dict[str, str]:
    """Secret name -> where the workload's container mounts it."""
    volumes = {v["name"]: v["secret"] for v in workload["spec"]["template"]["spec"].get("volumes", []) if "secret" in v}
    mounts = {m["name"]: m["mountPath"] for m in _containers(workload)[0].get("volumeMounts", [])}
    assert all(volume["defaultMode"] == 0o440 for volume in volumes.values()), volumes
    return {volume["secretName"]: mounts[name] for name, volume in volumes.items()}


@integration
@pytest.mark.parametrize("version", KUBERNETES_VERSIONS)
def test_every_manifest_validates_strictly(manifests: list[dict[str, Any]], version: str) -> None:
    for manifest in manifests:
        kubernetes_validate.validate(manifest, version, strict=True)
    assert all(m["metadata"].get("namespace") == "causeway" for m in manifests if m["kind"] != "Namespace")


@integration
def test_the_validator_rejects_an_unknown_field(manifests: list[dict[str, Any]]) -> None:
    broken = _find(manifests, "Deployment", "router")
    broken = {**broken, "spec": {**broken["spec"], "replica": 2}}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, KUBERNETES_VERSIONS[0], strict=True)


@integration
def test_router_is_a_deployment_behind_a_service_with_the_compose_config(manifests: list[dict[str, Any]],
                                                                         tmp_path: Path) -> None:
    import zenoh

    router = _find(manifests, "Deployment", "router")
    service = _find(manifests, "Service", "router")
    assert service["spec"]["selector"] == ROUTER and service["spec"]["ports"][0]["port"] == 7447
    assert router["spec"]["template"]["metadata"]["labels"].items() >= ROUTER.items()
    assert _containers(router)[0]["image"].startswith("eclipse/zenoh:1.")
    secret = _secret(manifests, "zenoh-router")
    assert _mounted_secrets(router) == {secret["metadata"]["name"]: "/etc/zenoh"}
    assert _containers(router)[0]["args"] == ["-c", "/etc/zenoh/router.json5"]
    ours = zenoh.Config.from_file(str(_secret_file(secret, "router.json5", tmp_path / "router.json5")))
    compose = zenoh.Config.from_file(str(REPO / "deploy" / "zenoh" / "router.json5"))
    for key in ("mode", "scouting/multicast/enabled", "plugins/rest/http_port"):
        assert ours.get_json(key) == compose.get_json(key), key
    assert json.loads(ours.get_json("listen/endpoints")) == ["tls/[::]:7447"], "links to the router may cross nodes"
    assert json.loads(ours.get_json("transport/auth/usrpwd/dictionary_file")) == "/etc/zenoh/router-users"
    assert set(secret["data"]) == {"router.json5", "router-users", "router-tls.pem", "router-tls.key",
                                   "router-roots.pem"}
    for key in ("listen_certificate", "listen_private_key", "root_ca_certificate"):
        path = json.loads(ours.get_json(f"transport/link/tls/{key}"))
        assert path.startswith("/etc/zenoh/") and path.rsplit("/", 1)[1] in secret["data"], (key, path)
    acl = json.loads(ours.get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny" and "causeway/k8s/control/all" in json.dumps(acl)
    assert _find(manifests, "Deployment", "router")["spec"]["template"]["spec"]["securityContext"]["fsGroup"] == 65534


@integration
def test_every_workload_mounts_exactly_its_roles_secret(manifests: list[dict[str, Any]], render: str,
                                                        tmp_path: Path) -> None:
    """Each workload mounts only its own role's Secret, whose user the router admits; and the router's access
    control is the one of the run, method and frames the workloads are configured with (the documented
    bus-secrets command's: an extractor overlay applied with the base's secrets would have its frames denied)."""
    import zenoh

    users = base64.b64decode(_secret(manifests, "zenoh-router")["data"]["router-users"]).decode()
    settings = _find(manifests, "ConfigMap", "causeway-settings")["data"]
    assert settings["CAUSEWAY_BUS_CREDENTIALS"] == CREDENTIALS
    for name, workload in _causeway_workloads(manifests).items():
        secret = _secret(manifests, f"bus-{name}")
        assert _mounted_secrets(workload) == {secret["metadata"]["name"]: CREDENTIALS.rsplit("/", 1)[0]}, name
        assert not any(e["name"] == "CAUSEWAY_BUS_CREDENTIALS" for e in _containers(workload)[0].get("env", []))
        assert workload["spec"]["template"]["spec"]["securityContext"]["fsGroup"] == 10001, name
        credentials = read_credentials(_secret_file(secret, "credentials", tmp_path / name))
        assert credentials.user == name and f"{name}:{credentials.password}\n" in users, name
    generated = {m["metadata"]["name"].rsplit("-", 1)[0] for m in manifests if m["kind"] == "Secret"}
    assert generated == {"zenoh-router"} | {f"bus-{name}" for name in CONFIGS}, "the base generates every role's"
    extractor = read_credentials(_secret_file(_secret(manifests, f"bus-{EXTRACTOR}"), "credentials", tmp_path / "x"))
    assert (f"{EXTRACTOR}:{extractor.password}\n" in users) == (EXTRACTOR in RENDERS[render]), "admitted where it runs"
    worker = parse_config(EnvWorkerConfig, [], _settings(manifests, _find(manifests, "Deployment", "env-worker")))
    roles = run_roles(worker.run_id, worker.method, dashboard_run="*", frames=worker.publish_frames,
                      latent=worker.frames_beside)
    wanted = zenoh.Config()  # as the router's file spells it: every unset field null
    wanted.insert_json5("access_control", json.dumps(access_control(roles)))
    router = json.loads(base64.b64decode(_secret(manifests, "zenoh-router")["data"]["router.json5"]))
    assert router["access_control"] == json.loads(wanted.get_json("access_control"))


@integration
def test_without_generated_secrets_nothing_renders(tmp_path: Path) -> None:
    """A fresh clone cannot apply an open router: kustomize names the missing files."""
    for directory, command in {"k8s": BUS_SECRETS, **EXTRACTOR_SECRETS}.items():
        assert command in (REPO / "deploy" / directory / "kustomization.yaml").read_text(), directory
    base = _copy_without_secrets(tmp_path / "k8s")
    for directory in RENDERS:
        result = _kustomize(base.parent / directory)
        assert result.returncode != 0 and "secrets/router.json5" in result.stderr, (directory, result.stderr)


@integration
def test_env_workers_are_a_deployment_scaled_by_an_hpa(manifests: list[dict[str, Any]]) -> None:
    workers = _find(manifests, "Deployment", "env-worker")
    hpa = _find(manifests, "HorizontalPodAutoscaler", "env-worker")
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": "Deployment", "name": "env-worker"}
    assert 1 <= hpa["spec"]["minReplicas"] < hpa["spec"]["maxReplicas"]
    metric = hpa["spec"]["metrics"][0]
    assert metric["type"] == "Resource" and metric["resource"]["name"] == "cpu"
    assert "cpu" in _containers(workers)[0]["resources"]["requests"], "CPU utilisation needs a CPU request"
    assert "replicas" in workers["spec"] and "volumeClaimTemplates" not in workers["spec"]


@integration
def test_stateful_services_are_statefulsets_with_volume_claims(manifests: list[dict[str, Any]], render: str) -> None:
    stateful = {m["metadata"]["name"] for m in manifests if m["kind"] == "StatefulSet"}
    assert stateful == STATEFUL & RENDERS[render]
    for name in stateful:
        workload = _find(manifests, "StatefulSet", name)
        assert workload["spec"]["replicas"] == 1 and workload["spec"]["serviceName"] == name
        claims = {c["metadata"]["name"]: c for c in workload["spec"]["volumeClaimTemplates"]}
        mounts = {m["name"]: m["mountPath"] for m in _containers(workload)[0]["volumeMounts"]}
        assert mounts["data"] == "/data" and "data" in claims, name
        assert workload["spec"]["template"]["spec"]["securityContext"]["fsGroup"] == 10001, "the image's user"
        assert _find(manifests, "Service", name)["spec"]["clusterIP"] == "None"


def _causeway_workloads(manifests: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {m["metadata"]["name"]: m for m in manifests if m["kind"] in ("Deployment", "StatefulSet")
            and m["metadata"]["name"] != "router"}


def _settings(manifests: list[dict[str, Any]], workload: dict[str, Any]) -> dict[str, str]:
    """The CAUSEWAY_* environment of the workload's container: the ConfigMap's, then its own ``env``."""
    shared = _find(manifests, "ConfigMap", "causeway-settings")["data"]
    own = {e["name"]: e["value"].replace("$(CAUSEWAY_RUN_ID)", shared["CAUSEWAY_RUN_ID"])
           for e in _containers(workload)[0].get("env", [])}
    return {**shared, **own}


@integration
def test_every_service_is_scraped_and_configured_with_known_settings(manifests: list[dict[str, Any]],
                                                                    render: str) -> None:
    workloads = _causeway_workloads(manifests)
    assert set(workloads) == RENDERS[render]
    for name, workload in workloads.items():
        annotations = workload["spec"]["template"]["metadata"]["annotations"]
        assert (annotations["prometheus.io/scrape"], annotations["prometheus.io/port"]) == ("true", "9100"), name
        container = _containers(workload)[0]
        assert container["command"] == ["python", "-m", f"services.{name.replace('-', '_')}"], name
        env = _settings(manifests, workload)
        known = {flag.env for flag in settings_parser(CONFIGS[name])[1]}
        assert set(env) <= known, f"{name}: unknown settings {set(env) - known}"
        cfg = parse_config(CONFIGS[name], [], env)
        assert (cfg.zenoh_connect, cfg.metrics_port, cfg.run_dir) == ("tls/router:7447", 9100, "/data/runs/k8s"), name
        assert cfg.bus_tls_root_ca == ROOT_CA, name


def _objects(manifests: list[dict[str, Any]]) -> dict[tuple[str, str], dict[str, Any]]:
    return {(m["kind"], m["metadata"]["name"]): m for m in manifests}


def _compose_default(value: object) -> str:
    """A compose environment value as compose resolves it with the variable unset (``${X:-d}`` -> ``d``)."""
    return re.sub(r"^\$\{\w+:-(.*)\}$", r"\1", str(value))


def _compose_override(overlay: str) -> dict[str, Any]:
    return yaml.safe_load((REPO / "deploy" / EXTRACTOR_OVERLAYS[overlay]).read_text())["services"]


def _worker_changes(overlay: str) -> dict[str, str]:
    """The env-workers' variables deploy/<overlay> sets: the policy's flag, or its compose override's (defaults)."""
    if overlay == OVERLAY:
        return {"CAUSEWAY_FOLLOW_POLICY": "true"}
    return {k: _compose_default(v) for k, v in _compose_override(overlay)["env-worker"]["environment"].items()}


@integration
@pytest.mark.parametrize("overlay", sorted(set(RENDERS) - {"k8s"}))
def test_an_overlay_is_the_base_plus_its_services_and_env_workers_set_for_them(
        generated: dict[str, Path], renders: dict[str, list[dict[str, Any]]], overlay: str) -> None:
    """Each overlay adds its services (a StatefulSet and a headless Service for one that checkpoints, else a
    Deployment), sets only the env-workers' variables that go with them (and, for FLAM, the stack's
    method), and changes nothing else; compared with the base rendered from the same secrets."""
    rendered = _rendered(generated[SECRETS[overlay]].parent / "k8s")
    base, ours = _objects(rendered), _objects(renders[overlay])
    new = RENDERS[overlay] - RENDERS["k8s"]
    added = {("StatefulSet" if name in STATEFUL else "Deployment", name) for name in new}
    added |= {("Service", name) for name in new & STATEFUL}
    assert set(ours) == set(base) | added and not set(base) & added
    worker, settings = ("Deployment", "env-worker"), ("ConfigMap", "causeway-settings")
    assert {key for key in base if ours[key] != base[key]} <= {worker, settings}
    changes = {**SETTINGS_CHANGES.get(overlay, {}), **_worker_changes(overlay)}
    assert _settings(renders[overlay], ours[worker]) == {**_settings(rendered, base[worker]), **changes}
    unchanged = copy.deepcopy(ours[worker])
    _containers(unchanged)[0]["env"] = _containers(base[worker])[0]["env"]
    assert unchanged == base[worker], "only the env-workers' env changes"
    assert ours[settings] == {**base[settings], "data": {**base[settings]["data"], **SETTINGS_CHANGES.get(overlay, {})}}


@integration
def test_the_overlay_runs_what_compose_runs_with_the_policy_profile(renders: dict[str, list[dict[str, Any]]]) -> None:
    """The services compose.yaml runs (``--profile policy``: the overlay; without: the base), and the
    policy profile's own settings at compose's defaults; the intrinsic-reward is a Deployment of one,
    never two at once (it saves nothing), and the env-workers follow the policy."""
    compose = yaml.safe_load((REPO / "compose.yaml").read_text())
    services = {name: service for name, service in compose["services"].items()
                if service.get("command", [""])[0] == "python"}
    assert {name for name, s in services.items() if "policy" in s.get("profiles", [])} == POLICY
    assert set(services) == RENDERS[OVERLAY]
    assert {name for name, s in services.items() if "profiles" not in s} == RENDERS["k8s"]
    shared = set(compose["x-causeway-env"])
    workloads = _causeway_workloads(renders[OVERLAY])
    for name in POLICY:
        env = _settings(renders[OVERLAY], workloads[name])
        wanted = {key: _compose_default(value) for key, value in services[name]["environment"].items()
                  if key not in shared}
        assert wanted and all(env.get(key) == value for key, value in wanted.items()), (name, wanted)
    cfg = {name: parse_config(CONFIGS[name], [], _settings(renders[OVERLAY], workloads[name])) for name in POLICY}
    assert cfg["policy-learner"].scored and cfg["intrinsic-reward"].reward == "preddiff"
    scorer = workloads["intrinsic-reward"]["spec"]
    assert scorer["replicas"] == 1 and scorer["strategy"] == {"type": "Recreate"}
    assert parse_config(EnvWorkerConfig, [], _settings(renders[OVERLAY], workloads["env-worker"])).follow_policy


@integration
@pytest.mark.parametrize("overlay", sorted(EXTRACTOR_OVERLAYS))
def test_an_extractor_overlay_runs_what_its_compose_override_runs(renders: dict[str, list[dict[str, Any]]],
                                                                  overlay: str) -> None:
    """The override's services (the extractor added, the env-workers changed as checked above), the extractor's
    mode, and one method: the override's default, the documented bus-secrets command's and every workload's."""
    override = _compose_override(overlay)
    compose = yaml.safe_load((REPO / "compose.yaml").read_text())["services"]
    assert set(override) - set(compose) == {EXTRACTOR} and set(override) == {"env-worker", EXTRACTOR}
    wanted = {key: _compose_default(value) for key, value in override[EXTRACTOR]["environment"].items()}
    cfg = {name: parse_config(CONFIGS[name], [], _settings(renders[overlay], w))
           for name, w in _causeway_workloads(renders[overlay]).items()}
    assert cfg[EXTRACTOR].mode == wanted["CAUSEWAY_MODE"]
    command = shlex.split(EXTRACTOR_SECRETS[overlay])
    methods = {c.method for c in cfg.values()} | {wanted["CAUSEWAY_METHOD"], command[command.index("--method") + 1]}
    assert len(methods) == 1, methods


@integration
def test_every_link_to_the_router_is_tls_with_the_ca_mounted_beside_the_credentials(
        manifests: list[dict[str, Any]], tmp_path: Path) -> None:
    """A pod's link to the router may cross nodes: every endpoint a workload connects to is ``tls/``, to a
    name the router's certificate carries, and the CA in its Secret is the one that signed it."""
    from cryptography import x509

    router_secret = _secret(manifests, "zenoh-router")
    certificate = x509.load_pem_x509_certificate(base64.b64decode(router_secret["data"]["router-tls.pem"]))
    names = set(certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
                .get_values_for_type(x509.DNSName))
    assert SERVICE_NAMES <= names, names
    shared = _find(manifests, "ConfigMap", "causeway-settings")["data"]
    for name, workload in _causeway_workloads(manifests).items():
        env = {**shared, **{e["name"]: e.get("value", "") for e in _containers(workload)[0].get("env", [])}}
        endpoints = [e.strip() for e in env["CAUSEWAY_ZENOH_CONNECT"].split(",")]
        assert all(e.startswith("tls/") and e[4:].rsplit(":", 1)[0] in names for e in endpoints), (name, endpoints)
        assert env["CAUSEWAY_BUS_TLS_ROOT_CA"] == ROOT_CA, name
        secret = _secret(manifests, f"bus-{name}")
        assert set(secret["data"]) == {"credentials", "ca.pem"}, name
        assert _mounted_secrets(workload)[secret["metadata"]["name"]] == ROOT_CA.rsplit("/", 1)[0], name
        ca = x509.load_pem_x509_certificate(base64.b64decode(secret["data"]["ca.pem"]))
        certificate.verify_directly_issued_by(ca)  # raises unless this CA signed the router's certificate
    assert not any("bus-ca.key" in s["data"] or any("PRIVATE KEY" in base64.b64decode(v).decode(errors="replace")
                                                      for k, v in s["data"].items() if k != "router-tls.key")
                   for s in manifests if s["kind"] == "Secret"), "the CA's key is mounted nowhere"
    settings_text = json.dumps(manifests)
    assert "tcp/router" not in settings_text


def _selects(selector: dict[str, Any], labels: dict[str, str]) -> bool:
    """Whether a LabelSelector (matchLabels, matchExpressions In/NotIn) selects ``labels``."""
    if any(labels.get(k) != v for k, v in selector.get("matchLabels", {}).items()):
        return False
    for expression in selector.get("matchExpressions", []):
        inside = labels.get(expression["key"]) in expression["values"]
        if inside != (expression["operator"] == "In"):
            return False
    return True


@integration
def test_network_policies_let_services_reach_only_the_router(manifests: list[dict[str, Any]]) -> None:
    policies = [m for m in manifests if m["kind"] == "NetworkPolicy"]
    deny = _find(manifests, "NetworkPolicy", "default-deny")["spec"]
    assert deny["podSelector"] == {} and set(deny["policyTypes"]) == {"Ingress", "Egress"}
    assert not deny.get("ingress") and not deny.get("egress")
    for name, workload in _causeway_workloads(manifests).items():
        labels = workload["spec"]["template"]["metadata"]["labels"]
        egress = [rule for p in policies if _selects(p["spec"]["podSelector"], labels)
                  for rule in p["spec"].get("egress", [])]
        assert egress, f"{name} may reach nothing"
        for rule in egress:
            for peer in rule["to"]:
                to_router = peer.get("podSelector", {}).get("matchLabels") == ROUTER and "namespaceSelector" not in peer
                to_dns = peer.get("podSelector", {}).get("matchLabels") == KUBE_DNS
                assert to_router or to_dns, f"{name} may reach {peer}"
            ports = {(p["protocol"], p["port"]) for p in rule["ports"]}
            assert ports in ({("TCP", 7447)}, {("UDP", 53), ("TCP", 53)}), f"{name}: {ports}"
        scrapes = [rule for p in policies if _selects(p["spec"]["podSelector"], labels)
                   for rule in p["spec"].get("ingress", []) if {"protocol": "TCP", "port": 9100} in rule["ports"]]
        assert any(peer.get("podSelector", {}).get("matchLabels") == PROMETHEUS for rule in scrapes
                   for peer in rule["from"]), f"Prometheus may not scrape {name}"
    router_labels = _find(manifests, "Deployment", "router")["spec"]["template"]["metadata"]["labels"]
    ingress = [rule for p in policies if _selects(p["spec"]["podSelector"], router_labels)
               for rule in p["spec"].get("ingress", [])]
    assert any({"protocol": "TCP", "port": 7447} in rule["ports"] for rule in ingress)


@integration
def test_a_pod_reaches_the_rendered_router_over_tls_by_the_service_name(renders: dict[str, list[dict[str, Any]]],
                                                                        tmp_path: Path) -> None:
    """The rendered router (its Secret's configuration, users and certificate) run in a network namespace
    where ``router`` names loopback: a client with the env-worker's Secret and the ConfigMap's endpoint
    opens its session over TLS; without the CA or without credentials it is refused."""
    import os
    import sys

    from tests.deploy.netns import make_host

    manifests = renders["k8s"]  # the overlay's router is the same object
    python = str(REPO / ".venv" / "bin" / "python") if (REPO / ".venv" / "bin" / "python").exists() else sys.executable
    router_dir, pod_dir = tmp_path / "etc-zenoh", tmp_path / "pod"
    router_dir.mkdir()
    pod_dir.mkdir()
    for key, value in _secret(manifests, "zenoh-router")["data"].items():
        text = base64.b64decode(value).decode()
        (router_dir / key).write_text(text.replace("/etc/zenoh/", f"{router_dir}/") if key == "router.json5" else text)
    for key, value in _secret(manifests, "bus-env-worker")["data"].items():
        (pod_dir / key).write_bytes(base64.b64decode(value))
    connect = _find(manifests, "ConfigMap", "causeway-settings")["data"]["CAUSEWAY_ZENOH_CONNECT"]
    one = make_host(f"k{os.getpid() % 100000}", sorted(SERVICE_NAMES))
    try:
        router = one.host.start([python, "-m", "tests.deploy.bus_probe", "router", "--config",
                                 str(router_dir / "router.json5"), "--listen", "tls/[::]:7447"], cwd=REPO)
        assert router.stdout is not None and router.stdout.readline(), router.stderr.read().decode()[-2000:]
        attempts = {"with_ca_and_credentials": ("--credentials", str(pod_dir / "credentials"),
                                                "--root-ca", str(pod_dir / "ca.pem")),
                    "without_ca": ("--credentials", str(pod_dir / "credentials")),
                    "without_credentials": ("--root-ca", str(pod_dir / "ca.pem"))}
        started = {name: one.host.start([python, "-m", "tests.deploy.bus_probe", "open", "--connect", connect, *bus],
                                        cwd=REPO) for name, bus in attempts.items()}
        opened = {}
        for name, process in started.items():
            out, err = process.communicate(timeout=60)
            assert process.returncode == 0, err.decode()[-2000:]
            opened[name] = json.loads(out.decode().strip().splitlines()[-1])["opened"]
        assert opened == {"with_ca_and_credentials": True, "without_ca": False, "without_credentials": False}, opened
    finally:
        one.close()
