"""Configuration of a local run (``causeway run``)."""
from __future__ import annotations

from dataclasses import dataclass

from causal.cdl import CDLConfig
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.runtime.config import doc

_CDL = CDLConfig()
COLLECTORS = ("random", "ppo", "sac")
INTRINSIC = ("none", "preddiff", "curiosity", "disagreement")
TASKS = {"": None, "match": "chemical-match"}
"""Task name -> the environment that poses it."""


@dataclass(frozen=True)
class RunConfig:
    """causeway run: start a router and every service locally, learn, report."""

    env: str = doc("chemical", "environment: chemical")
    graph: str = doc("full", "Chemical object graph: collider, chain, full or PATH.json")
    num_objects: int = doc(10, "Chemical: number of objects")
    cpt_seed: int = doc(0, "Chemical: seed of the fixed conditional probability tables")
    seed: int = doc(0, "run seed (worker i uses seed + i)")
    workers: int = doc(1, "number of env-worker processes")
    max_seconds: float = doc(900.0, "stop after this many seconds of wall time (0: no limit)")
    max_env_steps: int = doc(0, "stop after this many env steps (0: no limit); with --updates-per-env-step the "
                                "env-workers pause there and the run stops once the learner caught up")
    updates_per_env_step: float = doc(0.0, "dynamics-learner: at most this many updates per env step ingested, so "
                                           "collectors of different speeds train the same (0: as fast as possible)")
    catch_up_timeout_s: float = doc(600.0, "with --updates-per-env-step and --max-env-steps: longest wait, after the "
                                           "env-step budget, for the learner to catch up and the graph to follow")
    target_f1: float = doc(0.0, "stop once the graph's F1 reaches this (0: never)")
    target_metric: str = doc("f1", "metric compared with --target-f1: f1 (working threshold) or best_threshold_f1")
    run_id: str = doc("", "run id (default: derived from env, graph and time)")
    run_dir: str = doc("", "run directory (default: runs/<run_id>); an existing one is resumed")
    router_port: int = doc(7447, "TCP port of the Zenoh router on 127.0.0.1 (0: pick a free one)")
    metrics_base_port: int = doc(9100, "Prometheus ports: learner +1, evaluator +2, worker i +10+i (0: none)")
    steps_per_second: float = doc(2000.0, "throttle per env-worker (0: unthrottled)")
    lr: float = doc(_CDL.lr, "CDL Adam learning rate")
    lr_decay_updates: int = doc(_CDL.lr_decay_updates, "CDL: cosine decay of the learning rate from --lr to "
                                                       "--lr-final over this many updates (0: constant)")
    lr_final: float = doc(_CDL.lr_final, "CDL learning rate at the end of the decay")
    batch_size: int = doc(_CDL.batch_size, "CDL batch size")
    replay_capacity: int = doc(DynamicsLearnerConfig.replay_capacity,
                               "dynamics-learner: transitions kept in its replay (oldest dropped); raise it for "
                               "runs longer than this many env steps")
    feature_dim: int = doc(_CDL.feature_dim, "CDL feature size (and feature-network hidden width)")
    predictor_hidden: int = doc(_CDL.predictor_hidden, "CDL head hidden width")
    cmi_threshold: float = doc(_CDL.cmi_threshold, "CMI edge threshold, nats")
    eval_interval_s: float = doc(5.0, "minimum seconds between graph evaluations")
    publish_every_s: float = doc(5.0, "seconds between weight publications")
    dashboard_port: int = doc(8080, "port of the live causal-graph page on 127.0.0.1 (0: no dashboard)")
    checkpoint_every_s: float = doc(30.0, "seconds between service checkpoints")
    progress: bool = doc(True, "show live progress on the terminal")
    collector: str = doc("random", "collection policy: random, ppo or sac (the last two start a policy-learner "
                                   "whose newest weights the workers act with)")
    intrinsic: str = doc("none", "intrinsic reward of the policy: none, preddiff, curiosity or disagreement "
                                 "(all but none start an intrinsic-reward service)")
    task: str = doc("", "task on the environment: '' (none, reward-free) or match (env chemical-match)")
    abstraction: bool = doc(True, "mask the policy input to the learned abstraction (false: the dense baseline)")
    max_policy_lag: int = doc(4, "policy-learner: drop batches more than this many policy versions old")
    policy_hide: str = doc("", "policy-learner: factor-name prefixes the policy never sees (e.g. 'mk': the "
                               "manipulation markers)")
    intrinsic_coef: float = doc(1.0, "policy-learner: weight of the intrinsic reward")
    evaluate: bool = doc(True, "after a Chemical run: k-step prediction of the run's CDL model on ID and OOD "
                               "states and, with --task match, CEM and policy returns (summary.json, evaluation.png)")
