"""Configuration of a local run (``causeway run``): run-level settings composed with every service's
and every method's settings, each declared once, where it belongs.

* Run-wide settings every service shares (``--method``, ``--seed``, ``--heldout-fraction``,
  ``--checkpoint-every-s``): :class:`services.runtime.config.RunSettings`.
* A method's hyper-parameters: its own config class (``causal/``), flags ``--<method>-<field>``
  (``--cdl-lr``, ``--cdl-lr-decay-updates``, ...).
* Environment construction options (``--task``, ``--graph``, ``--num-objects``, ``--cpt-seed``, ...):
  :class:`envs.registry.EnvOptions`.
* A service's own settings: its config class, flags ``--<service>-<field>`` (``--learner-replay-capacity``,
  ``--evaluator-min-interval-s``, ``--worker-max-steps-per-second``, ``--policy-hide``, ``--intrinsic-eta``).
  Fields the wiring sets (ports, ids, the method, the algorithm the collector implies, ...) are not flags.

Where a run's default differs from a service's own default (a run publishes weights every 5 s, a
learner on its own every 3 s), the section states the run's value: ``section(..., publish_every_s=5.0)``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from causal.graph_metrics import REPORTED_SCORES
from causal.intrinsic import reward_names
from envs.registry import EnvOptions, env_names
from proto.settings import section
from services.dynamics_learner.config import DynamicsLearnerConfig, MethodConfigs
from services.env_worker.config import EnvWorkerConfig
from services.factor_extractor.config import FactorExtractorConfig
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.policy_learner.config import ALGOS, PolicyLearnerConfig
from services.runtime.config import SERVICE_FIELDS, RunSettings, config_from_dict, doc

COLLECTORS = ("random",) + ALGOS
INTRINSIC = ("none",) + reward_names()


@dataclass(frozen=True)
class RunConfig(RunSettings):
    """causeway run: start a router and every service locally, learn, report."""

    env: str = doc("chemical", "environment (envs.registry)", choices=env_names)
    workers: int = doc(1, "number of env-worker processes")
    max_workers: int = doc(64, "most env-worker processes a scale request may ask for (causeway scale); a request "
                               "for more is refused and logged, so a forged or mistyped one cannot start workers "
                               "without bound")
    max_seconds: float = doc(900.0, "stop after this many seconds of wall time (0: no limit)")
    max_env_steps: int = doc(0, "stop after this many env steps (0: no limit); with --learner-updates-per-env-step "
                                "the env-workers pause there and the run stops once the learner caught up")
    catch_up_timeout_s: float = doc(600.0, "with --learner-updates-per-env-step and --max-env-steps: longest wait, "
                                           "after the env-step budget, for the learner to catch up and the graph to follow")
    target_f1: float = doc(0.0, "stop once the graph's --target-metric reaches this (0: never)")
    target_metric: str = doc("f1", "graph score compared with --target-f1", choices=REPORTED_SCORES)
    stable_reports: int = doc(0, "stop once this many graph reports in a row have the same graph and the newest "
                                 "has no undecided entry: a stop without ground truth (0: never; see --stable-seconds)")
    stable_seconds: float = doc(0.0, "stop once the graph has been the same for this many seconds and the newest "
                                     "report has no undecided entry (0: never; with --stable-reports, both must hold)")
    run_id: str = doc("", "run id (default: derived from env, graph and time)")
    run_dir: str = doc("", "run directory (default: runs/<run_id>); an existing one is resumed")
    router_port: int = doc(7447, "TCP port of the Zenoh router on 127.0.0.1 (0: pick a free one)")
    bus_auth: bool = doc(True, "roles on the bus: the router admits only clients with this run's credentials "
                               "(fresh per start, in <run_dir>/secrets/, mode 600) and lets each role publish "
                               "and subscribe only its own keys (services.bus.roles); false: an open router")
    metrics_base_port: int = doc(9100, "Prometheus ports: learner +1, evaluator +2, worker i +10+i (0: none)")
    dashboard_port: int = doc(8080, "port of the live causal-graph page on 127.0.0.1 (0: no dashboard)")
    progress: bool = doc(True, "show live progress on the terminal")
    collector: str = doc("random", "collection policy: random (the env's default: uniform actions, or uniform "
                                   "skills where the env has them), ppo or sac (start a policy-learner whose "
                                   "newest weights the workers act with)", choices=COLLECTORS)
    intrinsic: str = doc("none", "intrinsic reward of the policy (all but none start an intrinsic-reward service)",
                         choices=INTRINSIC)
    label_latent_actions: bool = doc(False, "a FLAM run: the env-workers publish their frames beside the transitions and "
                                            "a factor-extractor labels every step with the learner's per-slot latent "
                                            "actions (LatentActions on latent/<worker>; the live page and summary.json "
                                            "show what each slot's labels carry)")
    evaluate: bool = doc(True, "after the run: the final graph on all held-out data and, where the env and "
                               "method have one, the post-run evaluation (Chemical: k-step prediction and, with "
                               "--task match, CEM and policy returns; summary.json, evaluation.png)")

    env_options: EnvOptions = section(EnvOptions, prefix="")
    models: MethodConfigs = section(MethodConfigs, prefix="")
    learner: DynamicsLearnerConfig = section(DynamicsLearnerConfig, prefix="learner",
                                             exclude=SERVICE_FIELDS + ("models",), publish_every_s=5.0)
    evaluator: GraphEvaluatorConfig = section(GraphEvaluatorConfig, prefix="evaluator",
                                              exclude=SERVICE_FIELDS + ("induced_graphs",),
                                              min_interval_s=5.0)
    worker: EnvWorkerConfig = section(EnvWorkerConfig, prefix="worker",
                                      exclude=SERVICE_FIELDS + ("env", "env_options", "worker_index", "follow_policy",
                                                                "skild", "frames_beside"),
                                      max_steps_per_second=2000.0)
    policy: PolicyLearnerConfig = section(PolicyLearnerConfig, prefix="policy",
                                          exclude=SERVICE_FIELDS + ("algo", "skills", "scored", "skild", "models"))
    intrinsic_reward: IntrinsicRewardConfig = section(IntrinsicRewardConfig, prefix="intrinsic",
                                                      exclude=SERVICE_FIELDS + ("reward",))
    extractor: FactorExtractorConfig = section(FactorExtractorConfig, prefix="extractor", exclude=SERVICE_FIELDS + ("mode",),
                                               help="the factor-extractor of a run with --worker-publish-frames true "
                                                    "(its slots) or --label-latent-actions true (FLAM's labels)")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.max_workers < self.workers:
            raise ValueError(f"max_workers must be >= workers ({self.workers}), got {self.max_workers}")
        for name in ("max_seconds", "max_env_steps", "catch_up_timeout_s", "target_f1", "stable_reports",
                     "stable_seconds"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("router_port", "metrics_base_port", "dashboard_port"):
            if not 0 <= getattr(self, name) <= 65535:
                raise ValueError(f"{name} must be a port in [0, 65535], got {getattr(self, name)}")


def load_run_config(run_dir: Path) -> RunConfig:
    """The configuration a run directory was started with (its ``config.json``; one written before
    settings moved into sections is read by flag name, see ``config_from_dict``)."""
    return config_from_dict(RunConfig, json.loads((Path(run_dir) / "config.json").read_text()))
