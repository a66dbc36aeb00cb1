"""dynamics-learner service shell: the only dynamics-learner file that touches the bus."""
from __future__ import annotations

import logging
import sys
import time

from proto import topics
from proto.messages import GraphReport, TransitionBatch
from services.bus.base import Transport
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.runtime.checkpoint import CONFIG_ERROR_EXIT
from services.runtime.shell import Inbox, ServiceShell, service_main

SERVICE = "dynamics-learner"
NONFINITE_LIMIT = 100
"""Updates in a row with a non-finite loss after which the learner gives up (a configuration error)."""


class NonFiniteTraining(RuntimeError):
    """Training cannot go on: every update's loss is NaN or infinite."""
log = logging.getLogger(SERVICE)


class _Metrics:
    def __init__(self, shell: ServiceShell) -> None:
        m = shell.metrics
        self.updates = m.counter("causeway_dynamics_updates", "Dynamics-model gradient updates")
        self.nll = m.gauge("causeway_dynamics_nll_nats", "Mean NLL per factor of the last update, by loss term (CDL: eq. 3.3)", ("term",))
        self.replay = m.gauge("causeway_replay_transitions", "Transitions in the replay buffer")
        self.env_steps = m.gauge("causeway_learner_env_steps", "Env steps seen by the learner (training + held-out)")
        self.version = m.gauge("causeway_weights_version", "Version of the last published weights")
        self.weights_bytes = m.counter("causeway_weights_bytes_published", "Bytes of weights published")
        self.update_seconds = m.histogram("causeway_update_seconds", "Duration of one dynamics-model update",
                                          (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0))
        self.checkpoints = m.counter("causeway_checkpoints", "Checkpoints written")
        self.lr = m.gauge("causeway_dynamics_learning_rate", "Learning rate of the next dynamics-model update (CDL: --cdl-lr-decay-updates)")
        self.ratio = m.gauge("causeway_dynamics_updates_per_env_step", "Updates per env step ingested so far")
        self.nonfinite = m.counter("causeway_dynamics_nonfinite_updates",
                                   "Updates skipped because the loss or gradient was not finite")
        self.live = m.gauge("causeway_dynamics_live_score",
                            "A score the trainer gives its model on fixed unseen data every few updates, by name "
                            "(FLAM: psnr in dB, dci_d, dci_c, dci_i ratios, slot<k>_kl in nats)", ("name",))
        self.lost = m.gauge("causeway_learner_transitions_lost",
                            "Transitions lost before reaching the model, from gaps in each worker life's seq, by "
                            "unit (batches; steps, counted at the length of the batch after the gap); resumed from "
                            "the checkpoint, so what a learner restart loses counts too; falls when a batch counted "
                            "lost arrives late", ("unit",))
        self.out_of_order = m.gauge("causeway_learner_batches_out_of_order",
                                    "TransitionBatches that arrived after a successor (late) or twice (duplicate), "
                                    "by kind; neither is counted lost twice", ("kind",))
        self.ratio_wait = m.counter("causeway_dynamics_ratio_wait_seconds",
                                    "Seconds the learner waited for env steps at --updates-per-env-step")

    def show_gaps(self, gaps: dict[str, float]) -> None:
        self.lost.labels(unit="batches").set(gaps["lost_batches"])
        self.lost.labels(unit="steps").set(gaps["lost_steps"])
        self.out_of_order.labels(kind="late").set(gaps["late_batches"])
        self.out_of_order.labels(kind="duplicate").set(gaps["duplicate_batches"])


def run(cfg: DynamicsLearnerConfig, transport: Transport | None = None) -> None:
    shell = ServiceShell(SERVICE, cfg, transport)
    metrics = _Metrics(shell)
    transitions = shell.inbox("transitions", TransitionBatch, maxsize=256)
    graphs = shell.inbox("graph", GraphReport, maxsize=8)
    shell.subscribe(topics.transitions(cfg.run_id), transitions)
    shell.subscribe(topics.graph(cfg.run_id, cfg.method), graphs)
    latest = shell.transport.serve_latest(topics.weights(cfg.run_id, cfg.method))
    spec = shell.wait_for_spec()
    if spec is None:
        shell.close()
        return
    core = DynamicsLearnerCore(cfg, spec)
    ckpt = shell.resume(core)
    last_publish = last_ckpt = time.monotonic()
    try:
        while not shell.stopping.is_set():
            shell.poll_control()
            _drain(core, transitions, graphs, shell)
            if shell.paused:
                time.sleep(0.02)
            elif core.may_update:
                _train(core, metrics)
            else:
                _wait_for_transitions(core, transitions, shell, metrics)
            now = time.monotonic()
            if core.ready and now - last_publish >= cfg.publish_every_s:
                _publish(shell, core, latest, metrics)
                last_publish = now
            last_ckpt = shell.checkpoint_if_due(core, ckpt, last_ckpt, metrics.checkpoints)
            metrics.replay.set(core.replay.size)
            metrics.env_steps.set(core.env_steps)
            metrics.show_gaps(core.gaps.stats())
            metrics.ratio.set(core.trainer.updates / max(core.env_steps, 1))
            metrics.lr.set(core.trainer.lr)
            shell.beat(core.progress())
            if cfg.max_updates and core.trainer.updates >= cfg.max_updates:
                break
    except NonFiniteTraining as exc:
        log.error("%s", exc)
        raise SystemExit(CONFIG_ERROR_EXIT) from exc
    finally:
        if core.trainer.updates:
            _publish(shell, core, latest, metrics)
        core.checkpoint(ckpt)
        log.info("stopped at update %d; checkpoint %s", core.trainer.updates, ckpt)
        shell.beat(core.progress(), force=True)
        latest.close()
        shell.close()


def _train(core: DynamicsLearnerCore, metrics: _Metrics) -> None:
    t0 = time.perf_counter()
    stats = core.train_step()
    metrics.update_seconds.observe(time.perf_counter() - t0)
    if "nonfinite_loss" in stats:
        metrics.nonfinite.inc()
        if stats["nonfinite_loss"] >= NONFINITE_LIMIT:
            raise NonFiniteTraining(f"the loss was not finite for {NONFINITE_LIMIT} updates in a row (no step was "
                                    f"taken): the learning rate is likely too high for this model")
        return
    metrics.updates.inc()
    for term, value in stats.items():
        if term.startswith("nll_"):
            metrics.nll.labels(term=term.removeprefix("nll_")).set(value)
        elif term.startswith("live_"):
            metrics.live.labels(name=term.removeprefix("live_")).set(value)


def _wait_for_transitions(core: DynamicsLearnerCore, transitions: Inbox, shell: ServiceShell, metrics: _Metrics) -> None:
    """Block on the inbox (no spin) until a batch arrives or 50 ms pass; time spent at the
    updates-per-env-step ratio (not in warm-up) is counted."""
    at_ratio, t0 = core.ready, time.perf_counter()
    item = transitions.get(timeout=0.05)
    if item is not None:
        shell.guarded(core.ingest, item[1])
    if at_ratio:
        metrics.ratio_wait.inc(time.perf_counter() - t0)


def _drain(core: DynamicsLearnerCore, transitions, graphs, shell: ServiceShell) -> None:
    for _, batch in transitions.drain():
        shell.guarded(core.ingest, batch)
    for _, report in graphs.drain():
        shell.guarded(core.apply_graph, report)


def _publish(shell: ServiceShell, core: DynamicsLearnerCore, latest, metrics: _Metrics) -> None:
    weights = core.weights()
    core.record_version(shell.checkpoint_path)
    metrics.weights_bytes.inc(shell.set_latest(latest, weights))
    metrics.version.set(core.version)


def main(argv: list[str] | None = None) -> None:
    service_main(SERVICE, DynamicsLearnerConfig, run, argv, models=True)


if __name__ == "__main__":
    main(sys.argv[1:])
