"""graph-evaluator service shell: the only graph-evaluator file that touches the bus."""
from __future__ import annotations

import logging
import sys
import time

from proto import topics
from proto.codec import encode
from causal.graph_metrics import REPORTED_SCORES
from proto.messages import GraphReport, LocalGraphReport, TransitionBatch, Weights
from services.bus.base import Transport
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.runtime.shell import ServiceShell, service_main

SERVICE = "graph-evaluator"
LOCAL_SCORES = ("roc_auc", "pr_auc", "best_f1", "f1", "positive_rate")
log = logging.getLogger(SERVICE)


class _Metrics:
    def __init__(self, shell: ServiceShell) -> None:
        m = shell.metrics
        self.scores = {name: m.gauge(f"causeway_graph_{name}_ratio", f"Learned graph {name} against the ground truth")
                       for name in REPORTED_SCORES}
        self.best_threshold = m.gauge("causeway_graph_best_threshold_nats", "Edge-score threshold with the best F1 (CMI: nats)")
        self.edges = m.gauge("causeway_graph_edges", "Edges in the learned graph (self-edges excluded)")
        self.undecided = m.gauge("causeway_graph_undecided_entries",
                                 "Graph entries the held-out data cannot yet decide (confidence interval across the rule's boundary)")
        self.classes = m.gauge("causeway_abstraction_factors", "Factors per abstraction class", ("class",))
        self.reports = m.counter("causeway_graph_reports", "GraphReports published")
        self.heldout = m.gauge("causeway_heldout_transitions", "Held-out transitions available for CMI")
        self.drawn = m.gauge("causeway_graph_eval_transitions",
                             "Held-out transitions the last evaluation drew (grows while a settled graph has undecided entries)")
        self.version = m.gauge("causeway_graph_weights_version", "Weights version of the last report")
        self.env_steps = m.gauge("causeway_graph_env_steps", "Env steps behind the last report")
        self.eval_seconds = m.histogram("causeway_graph_eval_seconds", "Duration of one all-pairs edge-score evaluation",
                                        (0.1, 0.25, 0.5, 1, 2, 4, 8, 16, 32))
        self.local_scores = {name: m.gauge(f"causeway_local_graph_{name}_ratio",
                                           f"Local graphs of held-out transitions: {name} against their true local graphs")
                             for name in LOCAL_SCORES}
        self.induced = m.counter("causeway_induced_graph_batches",
                                 "Batches whose induced local graphs were published (SkiLD: InducedGraphs)")
        self.induced_skipped = m.counter("causeway_induced_graph_batches_skipped",
                                         "Batches that got no induced graphs (no model yet)")
        self.local_reports = m.counter("causeway_local_graph_reports", "LocalGraphReports published")
        self.local_heldout = m.gauge("causeway_local_graph_heldout_transitions",
                                     "Held-out transitions kept with their true local graphs")
        self.local_seconds = m.histogram("causeway_local_graph_eval_seconds", "Duration of one local-graph evaluation",
                                         (0.1, 0.25, 0.5, 1, 2, 4, 8, 16, 32))

    def observe_local(self, report: LocalGraphReport, seconds: float) -> None:
        for name, gauge in self.local_scores.items():
            gauge.set(report.metrics[name])
        self.local_reports.inc()
        self.local_seconds.observe(seconds)

    def observe(self, report: GraphReport) -> None:
        for name, gauge in self.scores.items():
            if name in report.metrics:
                gauge.set(report.metrics[name])
        if "best_threshold" in report.metrics:
            self.best_threshold.set(report.metrics["best_threshold"])
        n = report.adjacency.shape[0]
        self.edges.set(int(report.adjacency.sum()) - int(report.adjacency[range(n), range(n)].sum()))
        if report.undecided is not None:
            self.undecided.set(int(report.undecided.sum()))
        for cls in ("controllable", "action_relevant", "action_irrelevant"):
            self.classes.labels(**{"class": cls}).set(len(getattr(report, cls)))
        self.reports.inc()
        self.version.set(report.weights_version)
        self.env_steps.set(report.env_steps)


def run(cfg: GraphEvaluatorConfig, transport: Transport | None = None) -> None:
    shell = ServiceShell(SERVICE, cfg, transport)
    metrics = _Metrics(shell)
    transitions = shell.inbox("transitions", TransitionBatch, maxsize=256)
    weights = shell.inbox("weights", Weights, maxsize=2)
    shell.subscribe(topics.transitions(cfg.run_id), transitions)
    shell.subscribe(topics.weights(cfg.run_id, cfg.method), weights)
    latest_graph = shell.transport.serve_latest(topics.graph(cfg.run_id, cfg.method))
    latest_local = shell.transport.serve_latest(topics.local(cfg.run_id, cfg.method))
    spec = shell.wait_for_spec()
    if spec is None:
        shell.close()
        return
    core = GraphEvaluatorCore(cfg, spec)
    ckpt = shell.resume(core)
    _catch_up(shell, core, cfg)
    last_eval, last_local, last_ckpt = 0.0, 0.0, time.monotonic()
    try:
        while not shell.stopping.is_set():
            shell.poll_control()
            for _, w in weights.drain():
                _load(core, w, shell)
            for _, batch in transitions.drain():
                if shell.guarded(core.ingest, batch) is not None and cfg.induced_graphs:
                    _publish_induced(shell, core, batch, metrics)
            metrics.heldout.set(core.heldout.size)
            now = time.monotonic()
            if not shell.paused and core.due and now - last_eval >= cfg.min_interval_s:
                t0, draw = time.perf_counter(), core.draw.size
                report = core.evaluate()
                metrics.eval_seconds.observe(time.perf_counter() - t0)
                metrics.drawn.set(report.num_heldout)
                if core.draw.size > draw:
                    log.info("graph unchanged for %d reports with %d undecided entries: the evaluation draw grows "
                             "from %d to %d held-out transitions", cfg.eval_growth_reports,
                             int(report.undecided.sum()), draw, core.draw.size)
                latest_graph.set(encode(report))
                metrics.observe(report)
                last_eval = now
            if not shell.paused and core.local_due and now - last_local >= cfg.min_interval_s:
                t0 = time.perf_counter()
                local = core.evaluate_local()
                latest_local.set(encode(local))
                metrics.observe_local(local, time.perf_counter() - t0)
                last_local = now
            if core.local is not None:
                metrics.local_heldout.set(core.local.ring.size)
            last_ckpt = shell.checkpoint_if_due(core, ckpt, last_ckpt)
            shell.beat({"heldout": core.heldout.size, "evaluated_version": core.evaluated_version,
                        "reports": len(core.history),
                        **(core.history[-1] if core.history else {}),
                        **(core.local.history[-1] if core.local is not None and core.local.history else {})})
            time.sleep(0.02)
    finally:
        core.checkpoint(ckpt)
        log.info("stopped after %d reports; checkpoint %s", len(core.history), ckpt)
        latest_graph.close()
        latest_local.close()
        shell.close()


def _publish_induced(shell: ServiceShell, core: GraphEvaluatorCore, batch: TransitionBatch, metrics: _Metrics) -> None:
    """SkiLD's induced graphs of every step of ``batch`` (none before the first weights)."""
    induced = core.induced(batch)
    if induced is None:
        metrics.induced_skipped.inc()
        return
    shell.publish(topics.induced(shell.cfg.run_id, core.kind, batch.worker_id), induced)
    metrics.induced.inc()


def _catch_up(shell: ServiceShell, core: GraphEvaluatorCore, cfg: GraphEvaluatorConfig) -> None:
    """A late (or restarted) evaluator asks for the current weights instead of waiting for the next ones."""
    for weights in shell.query(topics.weights(cfg.run_id, cfg.method), Weights):
        _load(core, weights, shell)


def _load(core: GraphEvaluatorCore, w: Weights, shell: ServiceShell) -> None:
    try:
        core.load_weights(w)
    except ValueError as exc:
        shell.metrics.reject("inconsistent")
        log.warning("rejected weights v%d: %s", w.version, exc)


def main(argv: list[str] | None = None) -> None:
    service_main(SERVICE, GraphEvaluatorConfig, run, argv, models=True)


if __name__ == "__main__":
    main(sys.argv[1:])
