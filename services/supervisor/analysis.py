"""After a local run: the summary, the final graph, the post-run evaluation, the plots.

:func:`analyse` turns what the supervisor saw (:class:`RunRecord`) and the run directory's
checkpoints into ``summary.json`` and the pictures beside it. Every step that reads models may fail
without losing the rest: a failure is logged or recorded in the summary, never raised (the run itself
is done by then).
"""
from __future__ import annotations

import json
import logging
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from causal.method import LatentActionScorer, SlotScorer
from causal.methods import get_method
from envs.registry import env_entry
from proto.messages import GraphReport, LocalGraphReport
from services.policy_learner.config import PolicyLearnerConfig
from services.runtime.checkpoint import load_checkpoint
from services.supervisor import evaluation
from services.supervisor import report as reporting
from services.supervisor import report_local as local_report
from services.supervisor import report_reward
from services.supervisor.config import RunConfig
from services.supervisor.final_graph import add_final_graph, add_final_local_graph, final_reports
from services.supervisor.wiring import env_kwargs, run_env_spec, service_configs

log = logging.getLogger("supervisor")


@dataclass
class RunRecord:
    """What the supervisor saw of a run, for its summary."""

    facts: dict[str, Any]
    """The run's own facts (ids, counts, wall time, why it stopped): the summary's first keys."""
    report: GraphReport | None
    history: list[dict[str, float]] = field(default_factory=list)
    policy_stats: dict[tuple[str, str], dict[str, float]] | None = None
    policy_timeline: list[tuple[float, str, str, float]] = field(default_factory=list)
    failure: str = ""
    local_report: LocalGraphReport | None = None
    local_history: list[dict[str, float]] = field(default_factory=list)
    live_history: list[dict[str, float]] = field(default_factory=list)


def analyse(cfg: RunConfig, run_dir: Path, record: RunRecord, stream: TextIO) -> dict[str, Any]:
    """Write ``summary.json`` and the plots; returns the summary's content."""
    report = record.report
    content = reporting.summary(report, record.facts, record.history)
    ok = cfg.evaluate and not record.failure and (report is not None or record.local_report is not None)
    # Over slots (--worker-publish-frames) the final model's factors are the extractor's: not rebuilt here.
    final, final_local = _final_reports(cfg, run_dir, stream) if ok and not cfg.worker.publish_frames else (None, None)
    if record.policy_stats is not None:
        content["policy"] = reporting.policy_summary(record.policy_stats, record.policy_timeline)
        reporting.plot_policy(content["policy"], run_dir / "policy.png")
    if record.local_report is not None:
        content["local_graph"] = {"evaluation": "last live report", **local_report.local_fields(record.local_report)}
        content["local_history"] = record.local_history
        local_report.plot_examples(record.local_report, run_dir / "local_graph.png")
        local_report.plot_curve(record.local_history, run_dir / "local_learning_curve.png")
    if final_local is not None:
        add_final_local_graph(content, final_local, run_dir)
    if record.live_history:
        content["live_history"] = record.live_history
        reporting.plot_live_scores(record.live_history, run_dir / "live_scores.png")
    method = get_method(cfg.method)
    if method.slots is not None and cfg.evaluate and not record.failure:
        stream.write("scoring the final model's slots (FG-ARI, no masks) ...\n")
        content["slots"] = _final_model_scores(cfg, run_dir, method.slots)
    if method.latent_actions is not None and cfg.evaluate and not record.failure:
        stream.write("scoring the final model's latent actions (10-step PSNR, DCI on unseen videos) ...\n")
        content["latent_actions"] = _final_model_scores(cfg, run_dir, method.latent_actions)
    if ok and report is not None and evaluation.applies(env_entry(cfg.env), get_method(cfg.method)):
        content["evaluation"] = _evaluate(cfg, run_dir, report, stream)
    if report is not None:
        reporting.plot_graphs(report, run_dir / "graph.png")
        reporting.plot_object_graphs(report, run_dir / "object_graph.png")
        reporting.plot_learning_curve(record.history, run_dir / "learning_curve.png")
        if report.reward_scores is not None:
            report_reward.plot_abstraction(report, run_dir / "abstraction.png")
    if final is not None:
        add_final_graph(content, final, run_dir)
    reporting.write_summary(run_dir / "summary.json", content)
    if "prediction" in content.get("evaluation", {}):
        evaluation.plot_evaluation(content["evaluation"], run_dir / "evaluation.png")
    return content


def _final_reports(cfg: RunConfig, run_dir: Path, stream: TextIO) -> tuple[GraphReport | None, LocalGraphReport | None]:
    """The final model's graph on all held-out data and its local graphs on every held-out
    transition with a true local graph (:mod:`services.supervisor.final_graph`)."""
    stream.write("final graph: edge scores of the final model on every held-out transition ...\n")
    try:
        final, local = final_reports(run_dir, service_configs(cfg, "")["graph-evaluator"], run_env_spec(cfg), stream)
    except Exception:  # noqa: BLE001 - the run itself is done
        log.exception("final graph evaluation failed")
        return None, None
    if final is not None:
        stream.write(f"final graph: {final.num_heldout:,} held-out transitions, {reporting.score_line(final.metrics)}\n")
    if local is not None:
        stream.write(f"final local graphs: {local.num_transitions:,} transitions, {local_report.score_line(local)}\n")
    return final, local


def _final_model_scores(cfg: RunConfig, run_dir: Path, scorer: SlotScorer | LatentActionScorer) -> dict[str, Any]:
    """A scorer's scores of the learner's final model (Dyn-O's slots: FG-ARI; FLAM's latent actions:
    PSNR and DCI); an error is recorded."""
    try:
        saved = load_checkpoint(run_dir / "checkpoints" / "dynamics-learner-0.pt")
        if saved is None:
            return {"error": "no dynamics-learner checkpoint"}
        model = evaluation.model_from_checkpoint(saved)
        return {"updates": int(saved["trainer"]["updates"]), **scorer.scores(model, run_env_spec(cfg))}
    except Exception as exc:  # noqa: BLE001 - reported in the summary
        log.exception("scoring the final model failed")
        return {"error": f"{type(exc).__name__}: {exc}"}


def _evaluate(cfg: RunConfig, run_dir: Path, report: GraphReport, stream: TextIO) -> dict[str, Any]:
    """The env's post-run evaluation suite on this run's final models (:mod:`services.supervisor.evaluation`);
    a failure is recorded in the summary."""
    stream.write("evaluating the run's model (prediction ID/OOD" + (", Match" if cfg.env_options.task == "match" else "") + ") ...\n")
    try:
        policy_cfg = service_configs(cfg, "")["policy-learner"]
        policy = load_policy(run_dir, policy_cfg, cfg) if cfg.collector != "random" else None
        return evaluation.evaluate_run(run_dir, env_entry(cfg.env), env_kwargs(cfg), report, policy)
    except Exception as exc:  # noqa: BLE001 - reported in the summary
        log.exception("post-run evaluation failed")
        return {"error": f"{type(exc).__name__}: {exc}"}


def load_policy(run_dir: Path, policy_cfg: PolicyLearnerConfig, cfg: RunConfig, deterministic: bool = True):
    """The policy-learner's last checkpointed policy as ``obs -> action`` (the mode, or sampled), or None.
    A policy over skills (``policy_cfg.skills``) returns the option to run next."""
    from services.policy_learner.core import PolicyLearnerCore

    path = run_dir / "checkpoints" / "policy-learner-0.pt"
    if not path.exists():
        return None
    core = PolicyLearnerCore(policy_cfg, run_env_spec(cfg))
    core.restore(path)
    return lambda obs: core.agent.act(obs, deterministic=deterministic)


def git_revision() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                              check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def print_summary(content: dict) -> None:
    keys = ("env", "method", "env_options", "seed", "env_steps", "updates", "wall_seconds", "stopped_because", "accuracy",
            "precision", "recall", "f1", "roc_auc", "best_threshold_f1")
    shown = {k: content.get(k) for k in keys}
    if "task" in content:
        shown["task"] = content["task"]
    if "local_graph" in content:
        local = content["local_graph"]
        shown["local_graph"] = {k: local.get(k) for k in ("evaluation", "num_transitions", "roc_auc", "pr_auc", "best_f1")}
    if "slots" in content:
        shown["slots"] = {k: content["slots"].get(k) for k in ("fg_ari", "updates", "error") if k in content["slots"]}
    if "latent_actions" in content:
        latent_keys = ("psnr", "dci_d", "dci_c", "dci_i", "dci_d_positions", "dci_c_positions", "dci_i_positions", "updates", "error")
        shown["latent_actions"] = {k: content["latent_actions"].get(k) for k in latent_keys if k in content["latent_actions"]}
    if "latent_labels" in content:
        shown["latent_labels"] = {k: content["latent_labels"].get(k) for k in ("labelled_steps", "slot_kl")}
    if "reward_graph" in content:
        shown["reward_graph"] = {k: content["reward_graph"].get(k) for k in ("learned_parents", "accuracy", "f1")}
        shown["task_abstraction"] = {k: content["task_abstraction"].get(k) for k in ("kept", "accuracy")}
    if "final_graph" in content:
        final = content["final_graph"]
        shown["final_graph"] = {k: final.get(k) for k in ("num_heldout", "edge_rule", "undecided_entries", "accuracy",
                                                          "f1", "best_threshold_f1",
                                                          "with_self_best_threshold_f1",
                                                          "with_self_best_threshold_accuracy")}
    print(json.dumps(shown, indent=1))
