"""The run's final causal graph (Algorithm 1, line 8): CMI of the final model on all held-out data.

While a run goes on, the graph-evaluator estimates CMI on ``eval_samples`` held-out transitions per
weights version and averages the estimates (live reports, cheap enough to follow training). After
training, the chapter evaluates the causal graph once (eq. 3.2) on the validation data; this does
that from the run's checkpoints: the dynamics-learner's final model, scored by the graph-evaluator's
own core on every transition of its held-out set (up to its ``heldout_capacity``). The run summary
carries it as ``final_graph`` beside the last live report, and ``graph.png`` / ``object_graph.png``
show it. On manipulation this is what removes the estimation noise of the live reports: a
2,000-transition estimate has a spread of ~0.007 nats per entry where the weak true edges sit at
~0.001 (``python -m benchmarks.cmi_estimation``).

``causeway final-graph --run-dir runs/X`` computes it for a finished run (one made before this
existed, or stopped early) and adds it to the run's summary.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, TextIO

from causal.method import export_tensors
from causal.methods import get_method
from proto.messages import EnvSpec, GraphReport, LocalGraphReport, Weights
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.runtime.checkpoint import load_checkpoint
from services.runtime.device import DEVICES, resolve_device
from services.supervisor import report as reporting
from services.supervisor import report_local as local_report
from services.supervisor.report_reward import plot_abstraction
from services.supervisor.evaluation import checkpoint_model_config, model_from_checkpoint
from services.supervisor.wiring import run_env_spec, service_configs


def final_core(run_dir: Path, evaluator_cfg: GraphEvaluatorConfig, spec: EnvSpec) -> GraphEvaluatorCore | None:
    """The graph-evaluator's core restored from the run's checkpoint, holding the learner's final
    model; None without both checkpoints or without held-out data."""
    learner = load_checkpoint(run_dir / "checkpoints" / "dynamics-learner-0.pt")
    core = GraphEvaluatorCore(evaluator_cfg, spec)
    if learner is None or not core.restore(run_dir / "checkpoints" / "graph-evaluator-0.pt") or not core.heldout.size:
        return None
    model = model_from_checkpoint(learner)
    config = checkpoint_model_config(learner)
    core.load_weights(Weights(model=json.loads(config)["model"], version=int(learner["version"]),
                              config_json=config,
                              tensors=export_tensors(model), updates=int(learner["trainer"]["updates"]),
                              env_steps=int(learner["env_steps"])))
    return core


def final_reports(run_dir: Path, evaluator_cfg: GraphEvaluatorConfig, spec: EnvSpec,
                  stream: TextIO | None = None) -> tuple[GraphReport | None, LocalGraphReport | None]:
    """The final model's global graph on the whole held-out set and its local graphs on every kept
    held-out transition with a true local graph; each None where the method or the data has none.
    With a ``stream``, the local graphs' progress goes to it (a line at most every 10 s)."""
    core = final_core(run_dir, evaluator_cfg, spec)
    if core is None:
        return None, None
    graph = core.evaluate_final() if core.method.global_graph is not None else None
    local = None
    if core.local is not None and core.local.ring.size:
        local = core.evaluate_local(every=True, progress=None if stream is None else _progress_lines(stream))
    return graph, local


def _progress_lines(stream: TextIO, every_s: float = 10.0) -> Callable[[int, int], None]:
    """``progress(done, total)`` writing ``final local graphs: done / total transitions (s)`` to
    ``stream`` when ``every_s`` seconds have passed since the last line (never for the last chunk:
    the caller reports the result)."""
    started = last = time.monotonic()

    def progress(done: int, total: int) -> None:
        nonlocal last
        now = time.monotonic()
        if done < total and now - last >= every_s:
            last = now
            stream.write(f"final local graphs: {done:,} / {total:,} transitions ({now - started:.0f}s)\n")
            stream.flush()

    return progress


def final_graph(run_dir: Path, evaluator_cfg: GraphEvaluatorConfig, spec: EnvSpec) -> GraphReport | None:
    """The final model's graph on the whole held-out set (:func:`final_reports`)."""
    core = final_core(run_dir, evaluator_cfg, spec)
    return core.evaluate_final() if core is not None and core.method.global_graph is not None else None


def add_final_graph(content: dict[str, Any], final: GraphReport, run_dir: Path) -> None:
    """``final_graph`` into a summary's ``content``; the graph plots redrawn from it."""
    content["final_graph"] = {"evaluation": "final model, CMI on every held-out transition (Algorithm 1, line 8)",
                              **reporting.graph_fields(final)}
    reporting.plot_graphs(final, run_dir / "graph.png", "final graph")
    reporting.plot_object_graphs(final, run_dir / "object_graph.png")
    if final.reward_scores is not None:
        plot_abstraction(final, run_dir / "abstraction.png", "final graph")


def add_final_local_graph(content: dict[str, Any], final: LocalGraphReport, run_dir: Path) -> None:
    """``local_graph`` (the final model's) into a summary's ``content``, the live one kept beside it."""
    if "local_graph" in content:
        content["local_graph_live"] = content["local_graph"]
    content["local_graph"] = {"evaluation": "final model, every kept held-out transition with a true local graph",
                              **local_report.local_fields(final)}
    local_report.plot_examples(final, run_dir / "local_graph.png", "final model")


def main(argv: list[str] | None = None) -> int:
    """``causeway final-graph --run-dir runs/X``: compute a finished run's final graph (and final local
    graph scores) into its summary."""
    from services.supervisor.config import load_run_config

    p = argparse.ArgumentParser(prog="causeway final-graph", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run-dir", type=Path, required=True, help="a finished run (with its checkpoints)")
    p.add_argument("--device", choices=DEVICES, default="auto",
                   help="where the CMI is computed (default auto: cuda if torch sees one, else cpu), whatever "
                        "device the run trained on: its checkpoints are device-independent")
    args = p.parse_args(argv)
    summary_path = args.run_dir / "summary.json"
    try:
        content = json.loads(summary_path.read_text())
        cfg = load_run_config(args.run_dir)
    except (OSError, ValueError, TypeError) as exc:
        print(f"causeway final-graph: {args.run_dir} is not a finished run: {exc}", file=sys.stderr)
        return 2
    started = time.perf_counter()
    try:
        resolve_device(args.device, get_method(cfg.method).devices)
    except ValueError as exc:
        print(f"causeway final-graph: {exc}", file=sys.stderr)
        return 2
    evaluator_cfg = dataclasses.replace(service_configs(cfg, "")["graph-evaluator"], device=args.device)
    final, local = final_reports(args.run_dir, evaluator_cfg, run_env_spec(cfg), sys.stdout)
    if final is None and local is None:
        print(f"causeway final-graph: {args.run_dir} has no learner and evaluator checkpoints", file=sys.stderr)
        return 1
    seconds = time.perf_counter() - started
    if final is not None:
        add_final_graph(content, final, args.run_dir)
        print(f"causeway final-graph: {final.num_heldout:,} held-out transitions ({seconds:.0f}s): "
              + reporting.score_line(final.metrics))
    if local is not None:
        add_final_local_graph(content, local, args.run_dir)
        print(f"causeway final-graph: local graphs of {local.num_transitions:,} held-out transitions: "
              + local_report.score_line(local))
    reporting.write_summary(summary_path, content)
    print(f"causeway final-graph: wrote {summary_path}")
    return 0
