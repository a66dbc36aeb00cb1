"""policy-learner service shell: the only policy-learner file that touches the bus."""
from __future__ import annotations

import logging
import sys
import time
from typing import Any, Callable

from proto import topics
from proto.messages import GraphReport, InducedGraphs, ScoredBatch, SkillBatch, TransitionBatch
from services.bus.base import Transport
from services.policy_learner.config import PolicyLearnerConfig
from services.policy_learner.core import DROP_REASONS, PolicyLearnerCore, Verdict
from causal.rl.policy_weights import MODEL
from causal.skild_policy import MODEL as SKILD_MODEL
from services.policy_learner.skild import DROP_REASONS as SKILD_DROP_REASONS, SkildLearnerCore
from services.runtime.shell import Inbox, ServiceShell, service_main

SERVICE = "policy-learner"
log = logging.getLogger(SERVICE)


class _Metrics:
    def __init__(self, shell: ServiceShell) -> None:
        m = shell.metrics
        self.updates = m.counter("causeway_policy_updates", "Policy gradient updates (PPO: one per rollout)")
        self.version = m.gauge("causeway_policy_version", "Version of the last published policy weights")
        self.lag = m.histogram("causeway_policy_lag_versions", "Policy lag of each received batch, in versions",
                               (0, 1, 2, 3, 4, 6, 8, 16, 32))
        self.dropped = m.counter("causeway_policy_dropped", "Batches dropped by the learner, by reason", ("reason",))
        for reason in DROP_REASONS:
            self.dropped.labels(reason=reason)
        self.update_seconds = m.histogram("causeway_policy_update_seconds", "Duration of one policy update",
                                          (0.001, 0.005, 0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5))
        self.weights_bytes = m.counter("causeway_policy_weights_bytes_published", "Bytes of policy weights published")

    def observe(self, verdict: Verdict) -> None:
        self.lag.observe(verdict.lag)
        if verdict.dropped:
            self.dropped.labels(reason=verdict.dropped).inc()


def run(cfg: PolicyLearnerConfig, transport: Transport | None = None) -> None:
    """Train on (scored) batches within the lag bound; publish every version (also to late queries)."""
    if cfg.skild:
        run_skild(cfg, transport)
        return
    shell = ServiceShell(SERVICE, cfg, transport)
    metrics = _Metrics(shell)
    source = shell.inbox("scored" if cfg.scored else "transitions", ScoredBatch if cfg.scored else TransitionBatch,
                         maxsize=256)
    graphs = shell.inbox("graph", GraphReport, maxsize=4)
    shell.subscribe(topics.scored(cfg.run_id) if cfg.scored else topics.transitions(cfg.run_id), source)
    shell.subscribe(topics.graph(cfg.run_id, cfg.method), graphs)

    def started(core: PolicyLearnerCore) -> None:
        log.info("published policy v%d (%s, max lag %d)", core.version, cfg.algo, cfg.max_policy_lag)

    def step(core: PolicyLearnerCore, publish: Callable[[], None]) -> bool:
        _drain(core, source, graphs, shell, metrics)
        if shell.paused or not core.ready:
            time.sleep(0.01)
        else:
            t0 = time.perf_counter()
            core.train_step()
            metrics.update_seconds.observe(time.perf_counter() - t0)
            metrics.updates.inc()
            if core.publish_due:
                publish()
        return bool(cfg.max_updates and core.updates >= cfg.max_updates)

    _serve(shell, cfg, MODEL, lambda spec: PolicyLearnerCore(cfg, spec), metrics, started, step)


def _serve(shell: ServiceShell, cfg: PolicyLearnerConfig, model: str, make_core: Callable[[Any], Any],
           metrics: _Metrics | _SkildMetrics, started: Callable[[Any], None],
           step: Callable[[Any, Callable[[], None]], bool]) -> None:
    """What both modes share: wait for the env spec, build and resume the core, publish its version,
    then run ``step`` (True when the update budget is spent) with the control polling, checkpoints and
    stats beats around it; the last checkpoint and beat on the way out, whatever ends the loop."""
    latest = shell.transport.serve_latest(topics.weights(cfg.run_id, model))
    spec = shell.wait_for_spec()
    if spec is None:
        latest.close()
        shell.close()
        return
    core = make_core(spec)
    ckpt = shell.resume(core)
    _publish(shell, core, latest, metrics)
    started(core)
    last_ckpt = time.monotonic()
    try:
        while not shell.stopping.is_set():
            shell.poll_control()
            done = step(core, lambda: _publish(shell, core, latest, metrics))
            last_ckpt = shell.checkpoint_if_due(core, ckpt, last_ckpt)
            shell.beat(core.progress())
            if done:
                break
    finally:
        core.checkpoint(ckpt)
        shell.beat(core.progress(), force=True)
        latest.close()
        shell.close()


def _drain(core: PolicyLearnerCore, source: Inbox, graphs: Inbox, shell: ServiceShell, metrics: _Metrics) -> None:
    for _, report in graphs.drain():
        if shell.guarded(core.apply_graph, report):
            log.info("policy input masked to factors %s", core.kept_factors)
    for _, message in source.drain():
        verdict = shell.guarded(core.ingest, message)
        if verdict is not None:
            metrics.observe(verdict)


def _publish(shell: ServiceShell, core, latest, metrics: _Metrics | _SkildMetrics) -> None:
    metrics.weights_bytes.inc(shell.set_latest(latest, core.weights()))
    metrics.version.set(core.version)


class _SkildMetrics:
    def __init__(self, shell: ServiceShell) -> None:
        m = shell.metrics
        self.updates = m.counter("causeway_skild_updates", "SkiLD updates, by part (skill Q-network, graph "
                                 "selector, task policy)", ("part",))
        self.steps = m.counter("causeway_skild_env_steps", "Env steps of skill data taken in, by phase", ("phase",))
        self.dropped = m.counter("causeway_skild_dropped", "SkillBatches dropped by the learner, by reason", ("reason",))
        self.phase = m.gauge("causeway_skild_task_phase", "1 once task learning started (the skills frozen), else 0")
        self.targets = m.gauge("causeway_skild_targets", "Target graphs in the graph history")
        self.version = m.gauge("causeway_policy_version", "Version of the last published policy weights")
        self.weights_bytes = m.counter("causeway_policy_weights_bytes_published", "Bytes of policy weights published")
        for part in ("skill", "selector", "task"):
            self.updates.labels(part=part)
        for phase in ("pretrain", "task"):
            self.steps.labels(phase=phase)
        for reason in SKILD_DROP_REASONS:
            self.dropped.labels(reason=reason)
        self.seen = {"skill": 0, "selector": 0, "task": 0, "pretrain": 0, "task_steps": 0}

    def observe(self, core: SkildLearnerCore) -> None:
        now = {"skill": core.updates, "selector": core.selector_updates, "task": core.task_updates,
               "pretrain": core.pretrain_steps, "task_steps": core.task_steps}
        for part in ("skill", "selector", "task"):
            self.updates.labels(part=part).inc(now[part] - self.seen[part])
        self.steps.labels(phase="pretrain").inc(now["pretrain"] - self.seen["pretrain"])
        self.steps.labels(phase="task").inc(now["task_steps"] - self.seen["task_steps"])
        self.seen = now
        self.phase.set(float(core.phase == "task"))
        self.targets.set(len(core.agent.history.targets))


def run_skild(cfg: PolicyLearnerConfig, transport: Transport | None = None) -> None:
    """SkiLD: skill pre-training then task learning from SkillBatches and their induced graphs; every
    version of the skill/task policies published on weights/skild-policy (also to late queries)."""
    shell = ServiceShell(SERVICE, cfg, transport)
    metrics = _SkildMetrics(shell)
    source = shell.inbox("skills", (SkillBatch, InducedGraphs), maxsize=512)
    shell.subscribe(topics.skills(cfg.run_id), source)
    if cfg.skild_graphs == "evaluator":
        shell.subscribe(topics.induced(cfg.run_id, cfg.method), source)

    def started(core: SkildLearnerCore) -> None:
        log.info("published SkiLD policy v%d (%s phase, induced graphs: %s)", core.version, core.phase, cfg.skild_graphs)

    def step(core: SkildLearnerCore, publish: Callable[[], None]) -> bool:
        for _, message in source.drain():
            reason = shell.guarded(core.ingest, message)
            if reason:
                metrics.dropped.labels(reason=reason).inc()
        if core.maybe_switch():
            log.info("pre-training budget spent (%d env steps, %d targets): task learning, skills frozen",
                     core.pretrain_steps, len(core.agent.history.targets))
        if shell.paused or not core.ready:
            time.sleep(0.01)
        else:
            core.train_step()
        if core.publish_due:
            publish()
        metrics.observe(core)
        return bool(cfg.max_updates and core.updates + core.task_updates >= cfg.max_updates)

    _serve(shell, cfg, SKILD_MODEL, lambda spec: SkildLearnerCore(cfg, spec), metrics, started, step)


def main(argv: list[str] | None = None) -> None:
    service_main(SERVICE, PolicyLearnerConfig, run, argv, models=True)


if __name__ == "__main__":
    main(sys.argv[1:])
