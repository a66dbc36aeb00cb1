"""intrinsic-reward service shell: the only intrinsic-reward file that touches the bus."""
from __future__ import annotations

import logging
import sys
from pathlib import Path

from proto import topics
from proto.messages import GraphReport, TransitionBatch, Weights
from services.bus.base import Transport
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.intrinsic_reward.core import IntrinsicRewardCore
from services.runtime.config import write_config
from services.runtime.shell import ServiceShell, service_main

SERVICE = "intrinsic-reward"
log = logging.getLogger(SERVICE)


class _Metrics:
    def __init__(self, shell: ServiceShell) -> None:
        m = shell.metrics
        self.published = m.counter("causeway_scored_batches_published", "ScoredBatches published")
        self.reward = m.histogram("causeway_intrinsic_reward", "Mean intrinsic reward of one scored batch",
                                  (-1.0, -0.5, -0.1, -0.01, 0.0, 0.01, 0.1, 0.5, 1.0, 5.0, 25.0))
        self.version = m.gauge("causeway_intrinsic_weights_version", "Version of the dynamics weights in use")
        self.graph = m.gauge("causeway_intrinsic_graph_version", "Weights version of the graph giving PA(j)")


def run(cfg: IntrinsicRewardConfig, transport: Transport | None = None) -> None:
    """Score every transition batch with the newest weights and graph; publish on scored/<worker>."""
    shell = ServiceShell(SERVICE, cfg, transport)
    metrics = _Metrics(shell)
    transitions = shell.inbox("transitions", TransitionBatch, maxsize=256)
    weights = shell.inbox("weights", Weights, maxsize=2)
    graphs = shell.inbox("graph", GraphReport, maxsize=4)
    shell.subscribe(topics.transitions(cfg.run_id), transitions)
    shell.subscribe(topics.weights(cfg.run_id, cfg.method), weights)
    shell.subscribe(topics.graph(cfg.run_id, cfg.method), graphs)
    spec = shell.wait_for_spec()
    if spec is None:
        shell.close()
        return
    core = IntrinsicRewardCore(cfg, spec)
    write_config(cfg, _config_path(cfg))
    _catch_up(shell, core, cfg, metrics)
    scored = 0
    try:
        while not shell.stopping.is_set():
            shell.poll_control()
            _load(shell, core, [w for _, w in weights.drain()], [g for _, g in graphs.drain()], metrics)
            item = transitions.get(timeout=0.05) if not shell.paused else None
            if item is not None:
                out = shell.guarded(core.score, item[1])
                if out is not None:
                    shell.publish(topics.scored(cfg.run_id, out.transitions.worker_id), out)
                    metrics.published.inc()
                    metrics.reward.observe(float(out.intrinsic_reward.mean()))
                    scored += 1
            shell.beat({"scored_batches": scored, "weights_version": core.weights_version,
                        "graph_version": core.graph_version})
    finally:
        shell.beat({"scored_batches": scored, "weights_version": core.weights_version}, force=True)
        shell.close()


def _load(shell: ServiceShell, core: IntrinsicRewardCore, weights: list[Weights], graphs: list[GraphReport],
          metrics: _Metrics) -> None:
    for w in weights:
        try:
            core.load_weights(w)
        except ValueError as exc:
            shell.metrics.reject("inconsistent")
            log.warning("rejected weights v%d: %s", w.version, exc)
    for g in graphs:
        shell.guarded(core.apply_graph, g)
    metrics.version.set(core.weights_version)
    metrics.graph.set(core.graph_version)


def _catch_up(shell: ServiceShell, core: IntrinsicRewardCore, cfg: IntrinsicRewardConfig, metrics: _Metrics) -> None:
    """A late (or restarted) scorer asks for the current weights and graph instead of waiting."""
    _load(shell, core, shell.query(topics.weights(cfg.run_id, cfg.method), Weights),
          shell.query(topics.graph(cfg.run_id, cfg.method), GraphReport), metrics)


def _config_path(cfg: IntrinsicRewardConfig) -> Path:
    return Path(cfg.run_dir) / "config" / f"{SERVICE}-{cfg.instance}.json"


def main(argv: list[str] | None = None) -> None:
    service_main(SERVICE, IntrinsicRewardConfig, run, argv, models=True)


if __name__ == "__main__":
    main(sys.argv[1:])
