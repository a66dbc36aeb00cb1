"""The stop rule without ground truth, run by run (issue 22): when each run stopped, why, and the graph
it stopped at.

Reads the ``summary.json`` of runs made with ``--stable-reports`` (and an fdr or fixed edge rule) and
prints one row per run: the graph, seed, rule (marked where the run's ``config.json`` kept the evaluator's
draw fixed), whether the stable-graph rule stopped it or a budget
did, its wall time and updates, the draw of held-out transitions its last report was estimated on
(the evaluator doubles it while a settled graph has undecided entries), that report's undecided
entries and its F1 / precision / recall, with the best-threshold F1 (the oracle, which needs the true
graph) and the F1 the chapter's fixed 0.02-nat threshold gives on the same CMI beside it; then one row
per graph (mean over its runs). Scores are the last live report's, what the run stopped on (run with
``--evaluate false``: no final graph replaces them). The false-discovery rate reached is one minus
the precision.

    python -m benchmarks.stop_table runs/fdr-grow-* [--out FILE]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from causal.graph_metrics import score_graph

FIXED_THRESHOLD = 0.02
"""The chapter's edge threshold (nats), the graph the FDR rule must not fall below."""
STABLE = "graph stable"


def row(run_dir: Path) -> dict[str, Any]:
    """One run's stop: its summary's facts and the scores of the report it stopped on."""
    s = json.loads((run_dir / "summary.json").read_text())
    options = s.get("env_options", {})
    rule = s.get("edge_rule", "fixed")
    if rule == "fdr":
        rule = f"fdr ({s['fdr']:g}, {s['bias'] if s.get('bias', 'fixed') != 'fixed' else format(s['min_cmi'], 'g')})"
    config = json.loads((run_dir / "config.json").read_text()) if (run_dir / "config.json").is_file() else {}
    evaluator = config.get("evaluator", {})
    if "eval_samples" in evaluator and evaluator.get("eval_samples_max", 0) <= evaluator["eval_samples"]:
        rule += f", draw fixed at {evaluator['eval_samples']:,}"  # the evaluator's draw may not grow
    return {"run": run_dir.name, "graph": f"{Path(str(options.get('graph', s['env']))).stem}, "
                                          f"{options.get('num_objects', '?')} objects",
            "seed": s.get("seed", 0), "rule": rule, "stopped": s["stopped_because"].startswith(STABLE),
            "stopped_because": s["stopped_because"], "seconds": float(s["wall_seconds"]),
            "updates": int(s["updates"]), "draw": int(s.get("num_heldout", 0)),
            "undecided": int(s.get("undecided_entries", 0)),
            **{k: float(s[k]) for k in ("f1", "precision", "recall", "best_threshold_f1")},
            "fixed_f1": float(score_graph(np.asarray(s["cmi"], dtype=float), np.asarray(s["true_graph"], dtype=np.uint8),
                                          FIXED_THRESHOLD)["f1"])}


def by_graph(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per graph and rule: runs, how many the rule stopped, mean seconds and F1, runs at the oracle's F1."""
    out = []
    for key in dict.fromkeys((r["graph"], r["rule"]) for r in rows):
        group = [r for r in rows if (r["graph"], r["rule"]) == key]
        out.append({"graph": key[0], "rule": key[1], "runs": len(group), "stopped": sum(r["stopped"] for r in group),
                    "seconds": float(np.mean([r["seconds"] for r in group])),
                    "f1": float(np.mean([r["f1"] for r in group])),
                    "fixed_f1": float(np.mean([r["fixed_f1"] for r in group])),
                    "best_threshold_f1": float(np.mean([r["best_threshold_f1"] for r in group])),
                    "at_oracle": sum(r["f1"] >= r["best_threshold_f1"] - 1e-9 for r in group)})
    return out


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = ["| run | graph | seed | rule | stopped after | updates | draw | undecided | F1 | precision / recall "
             "| F1 at fixed 0.02 | best-threshold F1 (oracle) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        why = "stable graph" if r["stopped"] else f"budget ({r['stopped_because']})"
        lines.append(f"| {r['run']} | {r['graph']} | {r['seed']} | {r['rule']} | {r['seconds']:.0f} s: {why} "
                     f"| {r['updates']:,} | {r['draw']:,} | {r['undecided']} | {r['f1']:.3f} "
                     f"| {r['precision']:.3f} / {r['recall']:.3f} | {r['fixed_f1']:.3f} | {r['best_threshold_f1']:.3f} |")
    lines += ["", "| graph | rule | runs | stopped by the rule | mean seconds | mean F1 at the stop "
                  "| mean F1 at fixed 0.02 | mean best-threshold F1 | runs at the oracle's F1 |",
              "|---|---|---|---|---|---|---|---|---|"]
    for g in by_graph(rows):
        lines.append(f"| {g['graph']} | {g['rule']} | {g['runs']} | {g['stopped']} | {g['seconds']:.0f} "
                     f"| {g['f1']:.3f} | {g['fixed_f1']:.3f} | {g['best_threshold_f1']:.3f} | {g['at_oracle']} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="run directories with a summary.json")
    p.add_argument("--out", type=Path, help="also write the rows as JSON here")
    args = p.parse_args(argv)
    missing = [str(d) for d in args.runs if not (d / "summary.json").is_file()]
    if missing:
        p.error(f"no summary.json in {', '.join(missing)}")
    rows = [row(d) for d in args.runs]
    print(markdown(rows))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"runs": rows, "graphs": by_graph(rows)}, indent=1))


if __name__ == "__main__":
    main()
