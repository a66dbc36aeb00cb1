"""Prometheus scrape config, Grafana provisioning and dashboard, and the services' exposition:
checked with promtool (config, every panel's PromQL as a recording rule, /metrics text)."""
from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from prometheus_client import CollectorRegistry, generate_latest

from services.runtime.metrics import ServiceMetrics
from tests.deploy import REPO, load_yaml_file, require_tool

integration = pytest.mark.integration
DASHBOARD = REPO / "deploy" / "grafana" / "dashboards" / "causeway.json"
SCRAPED_JOBS = {"env-worker", "dynamics-learner", "graph-evaluator", "dashboard", "policy-learner", "intrinsic-reward",
                "factor-extractor"}

# Metric names as Prometheus stores them (after prometheus_client's suffixing), per service.
COMMON_METRICS = {
    "causeway_messages_rejected_total", "causeway_messages_received_total", "causeway_messages_dropped_total",
    "causeway_queue_depth", "causeway_service_info", "causeway_process_start_time_seconds",
}
ENV_WORKER_METRICS = {
    "causeway_env_steps_total", "causeway_env_episodes_total", "causeway_transition_batches_published_total",
    "causeway_transition_bytes_published_total", "causeway_publish_seconds", "causeway_skill_options_chosen_total",
}
FOLLOWER_METRICS = {  # env-workers that follow a policy (--collector ppo/sac)
    "causeway_policy_version_in_use", "causeway_policy_weights_loaded_total", "causeway_policy_versions_skipped_total",
}
POLICY_LEARNER_METRICS = {
    "causeway_policy_updates_total", "causeway_policy_version", "causeway_policy_lag_versions",
    "causeway_policy_dropped_total", "causeway_policy_update_seconds", "causeway_policy_weights_bytes_published_total",
}
LEARNER_METRICS = {
    "causeway_dynamics_updates_total", "causeway_dynamics_nll_nats", "causeway_replay_transitions",
    "causeway_learner_env_steps", "causeway_weights_version", "causeway_weights_bytes_published_total",
    "causeway_update_seconds", "causeway_checkpoints_total",
    "causeway_dynamics_updates_per_env_step", "causeway_dynamics_ratio_wait_seconds_total",
    "causeway_dynamics_learning_rate", "causeway_dynamics_nonfinite_updates_total",
    "causeway_dynamics_live_score", "causeway_learner_transitions_lost", "causeway_learner_batches_out_of_order",
}
SKILD_LEARNER_METRICS = {  # the policy-learner of a --method skild run
    "causeway_skild_updates_total", "causeway_skild_env_steps_total", "causeway_skild_dropped_total",
    "causeway_skild_task_phase", "causeway_skild_targets", "causeway_policy_version",
    "causeway_policy_weights_bytes_published_total",
}
EXTRACTOR_METRICS = {  # the factor-extractor of a --worker-publish-frames run
    "causeway_slot_updates_total", "causeway_slot_loss", "causeway_slots_frozen_ratio", "causeway_frames_received_total",
    "causeway_slot_transitions_published_total", "causeway_slot_transition_bytes_published_total",
    "causeway_encode_seconds", "causeway_checkpoints_total", "causeway_slot_identity_ratio",
}
EVALUATOR_METRICS = {
    "causeway_graph_accuracy_ratio", "causeway_graph_precision_ratio", "causeway_graph_recall_ratio",
    "causeway_graph_f1_ratio", "causeway_graph_roc_auc_ratio", "causeway_graph_best_threshold_f1_ratio",
    "causeway_graph_best_threshold_nats", "causeway_graph_edges", "causeway_abstraction_factors",
    "causeway_graph_reports_total", "causeway_heldout_transitions", "causeway_graph_weights_version",
    "causeway_graph_env_steps", "causeway_graph_eval_seconds", "causeway_graph_identifiable_accuracy_ratio",
    "causeway_graph_identifiable_f1_ratio", "causeway_graph_identifiable_best_threshold_f1_ratio",
    "causeway_graph_with_self_accuracy_ratio", "causeway_graph_with_self_f1_ratio",
    "causeway_graph_with_self_best_threshold_f1_ratio",
    "causeway_local_graph_roc_auc_ratio", "causeway_local_graph_pr_auc_ratio", "causeway_local_graph_best_f1_ratio",
    "causeway_local_graph_f1_ratio", "causeway_local_graph_positive_rate_ratio", "causeway_local_graph_reports_total",
    "causeway_local_graph_heldout_transitions", "causeway_local_graph_eval_seconds",
    "causeway_graph_undecided_entries", "causeway_graph_eval_transitions",
    "causeway_induced_graph_batches_total", "causeway_induced_graph_batches_skipped_total",
}
HISTOGRAMS = {"causeway_publish_seconds", "causeway_update_seconds", "causeway_graph_eval_seconds",
              "causeway_local_graph_eval_seconds",
              "causeway_policy_lag_versions", "causeway_policy_update_seconds", "causeway_encode_seconds"}
KNOWN_METRICS = (COMMON_METRICS | ENV_WORKER_METRICS | FOLLOWER_METRICS | LEARNER_METRICS | EVALUATOR_METRICS
                 | POLICY_LEARNER_METRICS | SKILD_LEARNER_METRICS | EXTRACTOR_METRICS | {"up"})

# PromQL pieces that are not metric names: strings, label matchers, ranges, grouping clauses.
_NOT_NAMES = re.compile(r'"(?:[^"\\]|\\.)*"|\{[^}]*\}|\[[^\]]*\]'
                        r"|\b(?:by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)")
_IDENTIFIER = re.compile(r"\b([A-Za-z_:][A-Za-z0-9_:]*)\b(?!\s*\()")
_KEYWORDS = {"and", "or", "unless", "bool", "offset", "inf", "nan"}


def metric_names(expr: str) -> set[str]:
    """Metric names a PromQL expression selects (identifiers that are not functions or keywords)."""
    return {name for name in _IDENTIFIER.findall(_NOT_NAMES.sub(" ", expr)) if name.lower() not in _KEYWORDS}


def _known(name: str) -> bool:
    base = re.sub(r"_(bucket|sum|count)$", "", name)
    return name in KNOWN_METRICS or (base in HISTOGRAMS and base != name)


def _panels() -> list[dict[str, Any]]:
    dashboard = json.loads(DASHBOARD.read_text())
    flat = []
    for panel in dashboard["panels"]:
        flat.append(panel)
        flat.extend(panel.get("panels", []))
    return flat


def _queries() -> list[tuple[int, str, str]]:
    return [(p["id"], t["refId"], t["expr"]) for p in _panels() if p["type"] != "row" for t in p["targets"]]


def _promtool(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([require_tool("promtool"), *args], input=stdin, cwd=REPO, capture_output=True,
                          text=True, timeout=60)


# ------------------------------------------------------------------------------------ prometheus
@integration
def test_promtool_accepts_the_scrape_config() -> None:
    result = _promtool("check", "config", "deploy/prometheus/prometheus.yml")
    assert result.returncode == 0, result.stdout + result.stderr


@integration
def test_every_service_is_scraped_every_5s_through_dns() -> None:
    """Replicas are found by DNS, and a service outside the running profiles has no (down) target."""
    config = load_yaml_file("deploy/prometheus/prometheus.yml")
    assert config["global"]["scrape_interval"] == "5s"
    jobs = {job["job_name"]: job for job in config["scrape_configs"]}
    assert set(jobs) == SCRAPED_JOBS
    for name in SCRAPED_JOBS:
        assert jobs[name]["dns_sd_configs"] == [
            {"names": [name], "type": "A", "port": 9100, "refresh_interval": "10s"}], name
        assert "static_configs" not in jobs[name], name


# ------------------------------------------------------------------------------------ grafana
@integration
def test_grafana_provisions_the_prometheus_datasource_and_the_dashboard_folder() -> None:
    datasources = load_yaml_file("deploy/grafana/provisioning/datasources/prometheus.yml")["datasources"]
    assert [(d["uid"], d["type"], d["url"]) for d in datasources] == [
        ("prometheus", "prometheus", "http://prometheus:9090")]
    providers = load_yaml_file("deploy/grafana/provisioning/dashboards/dashboards.yml")["providers"]
    compose = (REPO / "compose.yaml").read_text()
    for provider in providers:
        assert f"./deploy/grafana/dashboards:{provider['options']['path']}:ro" in compose


def test_dashboard_panels_have_unique_ids_and_prometheus_queries() -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    assert dashboard["uid"] and 36 <= dashboard["schemaVersion"] <= 41
    panels = _panels()
    ids = [p["id"] for p in panels]
    assert len(ids) == len(set(ids)), "duplicate panel ids"
    for panel in panels:
        if panel["type"] == "row":
            continue
        assert panel["datasource"]["uid"] == "prometheus", panel["title"]
        assert panel["targets"], panel["title"]
        for target in panel["targets"]:
            assert target["expr"].strip(), f"{panel['title']} {target['refId']} has no expr"
            assert target["datasource"]["uid"] == "prometheus", panel["title"]


def test_dashboard_uses_only_metrics_the_services_export() -> None:
    used = set().union(*(metric_names(expr) for _, _, expr in _queries()))
    assert used, "no metric names found"
    assert {name for name in used if not _known(name)} == set()
    assert "causeway_graph_f1_ratio" in used and "up" in used


def test_metric_name_extraction() -> None:
    expr = 'histogram_quantile(0.95, sum by (le, instance) (rate(causeway_publish_seconds_bucket{job="x"}[5m])))'
    assert metric_names(expr) == {"causeway_publish_seconds_bucket"}
    assert metric_names('time() - causeway_process_start_time_seconds') == {"causeway_process_start_time_seconds"}
    assert metric_names('up{job=~"a|b"} and on (job) foo offset 5m') == {"up", "foo"}


@integration
def test_every_dashboard_query_is_valid_promql(tmp_path: Path) -> None:
    rules = [{"record": f"causeway:panel_{pid}_{ref}", "expr": expr} for pid, ref, expr in _queries()]
    path = tmp_path / "dashboard_rules.yml"
    path.write_text(json.dumps({"groups": [{"name": "dashboard", "rules": rules}]}))  # JSON is YAML
    result = _promtool("check", "rules", str(path))
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"{len(rules)} rules found" in result.stdout


# ------------------------------------------------------------------------------------ exposition
def _learner_registry() -> CollectorRegistry:
    from services.dynamics_learner.service import _Metrics

    common = ServiceMetrics("dynamics-learner", "0")
    metrics = _Metrics(SimpleNamespace(metrics=common))
    metrics.nll.labels(term="full").set(1.25)
    metrics.update_seconds.observe(0.02)
    metrics.updates.inc()
    common.received.labels(type="TransitionBatch").inc(3)
    common.queue_depth.labels(queue="transitions").set(2)
    return common.registry


def _evaluator_registry() -> CollectorRegistry:
    from services.graph_evaluator.service import _Metrics

    common = ServiceMetrics("graph-evaluator", "0")
    metrics = _Metrics(SimpleNamespace(metrics=common))
    metrics.classes.labels(**{"class": "controllable"}).set(4)
    metrics.scores["f1"].set(0.75)
    metrics.eval_seconds.observe(1.5)
    common.dropped.labels(reason="stale").inc()
    return common.registry


def _env_worker_registry() -> CollectorRegistry:
    """As services/env_worker/service.py registers them (inline there, so mirrored here)."""
    common = ServiceMetrics("env-worker", "host-1")
    common.counter("causeway_env_steps", "Environment steps taken").inc(256)
    common.counter("causeway_env_episodes", "Episodes finished")
    common.counter("causeway_transition_batches_published", "TransitionBatches published").inc()
    common.counter("causeway_transition_bytes_published", "Bytes of TransitionBatches published").inc(1 << 16)
    common.histogram("causeway_publish_seconds", "Time to publish one batch", (0.001, 0.01, 0.1)).observe(0.002)
    common.counter("causeway_skill_options_chosen", "Skills started", ("option", "policy")).labels(
        option="grasp:unm", policy="learned").inc(3)
    return common.registry


def _follower_registry() -> CollectorRegistry:
    from services.env_worker.service import _PolicyFollower

    common = ServiceMetrics("env-worker", "0")
    shell = SimpleNamespace(metrics=common, inbox=lambda *a, **k: None, subscribe=lambda *a: None)
    follower = _PolicyFollower(shell, None, SimpleNamespace(run_id="r", skild=False))
    follower.in_use.set(3)
    return common.registry


def _policy_learner_registry() -> CollectorRegistry:
    from services.policy_learner.service import _Metrics

    common = ServiceMetrics("policy-learner", "0")
    metrics = _Metrics(SimpleNamespace(metrics=common))
    metrics.version.set(4)
    metrics.lag.observe(1)
    metrics.update_seconds.observe(0.05)
    return common.registry


def _skild_learner_registry() -> CollectorRegistry:
    from services.policy_learner.service import _SkildMetrics

    common = ServiceMetrics("policy-learner", "0")
    metrics = _SkildMetrics(SimpleNamespace(metrics=common))
    metrics.phase.set(1)
    metrics.targets.set(12)
    return common.registry


def _extractor_registry() -> CollectorRegistry:
    from services.factor_extractor.service import _Metrics

    common = ServiceMetrics("factor-extractor", "0")
    metrics = _Metrics(SimpleNamespace(metrics=common))
    metrics.loss.labels(term="reconstruction").set(0.02)
    metrics.encode_seconds.observe(0.03)
    return common.registry


def _families(registry: CollectorRegistry) -> set[str]:
    """Metric names as stored by Prometheus: counters get ``_total``; ``_created`` series skipped."""
    return {family.name + ("_total" if family.type == "counter" else "") for family in registry.collect()}


def test_known_metric_lists_match_the_services_registries() -> None:
    assert _families(_learner_registry()) == COMMON_METRICS | LEARNER_METRICS
    assert _families(_evaluator_registry()) == COMMON_METRICS | EVALUATOR_METRICS
    assert _families(_env_worker_registry()) == COMMON_METRICS | ENV_WORKER_METRICS
    assert _families(_follower_registry()) == COMMON_METRICS | FOLLOWER_METRICS
    assert _families(_policy_learner_registry()) == COMMON_METRICS | POLICY_LEARNER_METRICS
    assert _families(_skild_learner_registry()) == COMMON_METRICS | SKILD_LEARNER_METRICS
    assert _families(_extractor_registry()) == COMMON_METRICS | EXTRACTOR_METRICS


@integration
@pytest.mark.parametrize("registry", [_env_worker_registry, _learner_registry, _evaluator_registry,
                                      _policy_learner_registry, _skild_learner_registry, _extractor_registry],
                         ids=["env-worker", "dynamics-learner", "graph-evaluator", "policy-learner",
                              "policy-learner-skild", "factor-extractor"])
def test_promtool_accepts_the_metrics_exposition(registry) -> None:
    result = _promtool("check", "metrics", stdin=generate_latest(registry()).decode())
    report = result.stdout + result.stderr
    if report.strip():
        print(report)  # lint advice (exit 3) is fine; a parse error (exit 1) is not
    assert result.returncode in (0, 3) and "error" not in report.lower(), report
