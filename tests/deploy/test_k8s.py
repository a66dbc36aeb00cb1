"""deploy/k8s: rendered offline by ``kubectl kustomize`` and validated against the Kubernetes API
schemas that ``kubernetes-validate`` bundles (strict: unknown fields are errors); then the shape
issue 21 asks for (router Deployment + Service, env-workers scaled by an HPA, learners as
StatefulSets with volume claims, scrape annotations, services reaching only the router) and
settings every service's config parser accepts."""
from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import pytest

from services.dashboard.config import DashboardConfig
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.env_worker.config import EnvWorkerConfig
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.runtime.config import parse_config, settings_parser
from tests.deploy import REPO, require_tool

kubernetes_validate = pytest.importorskip("kubernetes_validate", reason="pip install -e '.[test]' installs it")
yaml = pytest.importorskip("yaml")

integration = pytest.mark.integration
KUBERNETES_VERSIONS = ("1.30.0", kubernetes_validate.latest_version())
CONFIGS = {"env-worker": EnvWorkerConfig, "dynamics-learner": DynamicsLearnerConfig,
           "graph-evaluator": GraphEvaluatorConfig, "dashboard": DashboardConfig}
ROUTER = {"app.kubernetes.io/part-of": "causeway", "app.kubernetes.io/component": "router"}
KUBE_DNS = {"k8s-app": "kube-dns"}


@pytest.fixture(scope="module")
def manifests() -> list[dict[str, Any]]:
    """``kubectl kustomize deploy/k8s``: every object, namespace applied."""
    result = subprocess.run([require_tool("kubectl"), "kustomize", str(REPO / "deploy" / "k8s")],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    return [doc for doc in yaml.safe_load_all(result.stdout) if doc]


def _find(manifests: list[dict[str, Any]], kind: str, name: str) -> dict[str, Any]:
    found = [m for m in manifests if m["kind"] == kind and m["metadata"]["name"] == name]
    assert len(found) == 1, f"{kind}/{name}: {len(found)} found"
    return found[0]


def _containers(workload: dict[str, Any]) -> list[dict[str, Any]]:
    return workload["spec"]["template"]["spec"]["containers"]


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
    (tmp_path / "router.json5").write_text(_find(manifests, "ConfigMap", "zenoh-router")["data"]["router.json5"])
    ours = zenoh.Config.from_file(str(tmp_path / "router.json5"))
    compose = zenoh.Config.from_file(str(REPO / "deploy" / "zenoh" / "router.json5"))
    for key in ("mode", "listen/endpoints", "scouting/multicast/enabled", "plugins/rest/http_port"):
        assert ours.get_json(key) == compose.get_json(key), key


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
@pytest.mark.parametrize("name", ["dynamics-learner", "graph-evaluator"])
def test_stateful_services_are_statefulsets_with_volume_claims(manifests: list[dict[str, Any]], name: str) -> None:
    workload = _find(manifests, "StatefulSet", name)
    assert workload["spec"]["replicas"] == 1 and workload["spec"]["serviceName"] == name
    claims = {c["metadata"]["name"]: c for c in workload["spec"]["volumeClaimTemplates"]}
    mounts = {m["name"]: m["mountPath"] for m in _containers(workload)[0]["volumeMounts"]}
    assert mounts["data"] == "/data" and "data" in claims
    assert workload["spec"]["template"]["spec"]["securityContext"]["fsGroup"] == 10001, "the image's user"
    assert _find(manifests, "Service", name)["spec"]["clusterIP"] == "None"


def _causeway_workloads(manifests: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {m["metadata"]["name"]: m for m in manifests if m["kind"] in ("Deployment", "StatefulSet")
            and m["metadata"]["name"] != "router"}


@integration
def test_every_service_is_scraped_and_configured_with_known_settings(manifests: list[dict[str, Any]]) -> None:
    workloads = _causeway_workloads(manifests)
    assert set(workloads) == set(CONFIGS)
    shared = _find(manifests, "ConfigMap", "causeway-settings")["data"]
    for name, workload in workloads.items():
        annotations = workload["spec"]["template"]["metadata"]["annotations"]
        assert (annotations["prometheus.io/scrape"], annotations["prometheus.io/port"]) == ("true", "9100"), name
        container = _containers(workload)[0]
        assert container["command"] == ["python", "-m", f"services.{name.replace('-', '_')}"], name
        env = dict(shared)
        env.update({e["name"]: e["value"].replace("$(CAUSEWAY_RUN_ID)", shared["CAUSEWAY_RUN_ID"])
                    for e in container.get("env", [])})
        known = {flag.env for flag in settings_parser(CONFIGS[name])[1]}
        assert set(env) <= known, f"{name}: unknown settings {set(env) - known}"
        cfg = parse_config(CONFIGS[name], [], env)
        assert (cfg.zenoh_connect, cfg.metrics_port, cfg.run_dir) == ("tcp/router:7447", 9100, "/data/runs/k8s"), name


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
    router_labels = _find(manifests, "Deployment", "router")["spec"]["template"]["metadata"]["labels"]
    ingress = [rule for p in policies if _selects(p["spec"]["podSelector"], router_labels)
               for rule in p["spec"].get("ingress", [])]
    assert any({"protocol": "TCP", "port": 7447} in rule["ports"] for rule in ingress)
