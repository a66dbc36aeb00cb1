"""Score finished runs again, from their ``summary.json``, with the current scoring.

A run's summary keeps the final smoothed CMI matrix and the true graph, so a scoring added after
the run (``with_self_*``: every entry, self-edges included and kept, the scoring Table 3.1's
numbers imply; see :mod:`causal.graph_metrics`) can be computed for it without running it again.
Prints a markdown table (plain and with-self scores at the working threshold and at the best
threshold, found by :func:`causal.graph_metrics.best_threshold`'s exact search, with the chapter's
figures as the last row where they exist) and writes the scores as JSON.

    python -m benchmarks.rescore_runs runs/manip-1w runs/manip-decay [--out benchmark-results/rescore.json]
    python -m benchmarks.rescore_runs runs/manip-decay-s1 runs/manip-decay-s2 runs/manip-decay-s3 --mean
    python -m benchmarks.rescore_runs runs/manip-ev-s0 --graph final

``--graph final`` scores each run's final graph (the final model's CMI on all its held-out data,
``summary.json``'s ``final_graph``; :mod:`services.supervisor.final_graph`) instead of its last live
report.

``--mean`` (for seeds of one configuration) adds a row of mean ± sample standard deviation per
environment, the form of the chapter's 3-seed figures. A single report's best-threshold F1 moves by
a few hundredths from one report to the next, so ``--window S`` adds a second table: each run's
scores averaged over its reports of the last S seconds (``history`` in ``summary.json``; runs
started before a score existed have no value for it there).

The CMI in ``summary.json`` is rounded to 5 decimals; scores computed from it can differ from the
run's own in the last digit where an entry sits on a threshold.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from causal.graph_metrics import score_graph

CHAPTER = {"manipulation": {"accuracy": (0.902, 0.003), "recall": (0.612, 0.009), "precision": (0.980, 0.006),
                            "f1": (0.754, 0.008), "roc_auc": (0.805, 0.005)}}
"""Table 3.1, CDL: (mean, standard deviation) over 3 seeds, each at its best threshold."""

COLUMNS = (("with_self_best_threshold_f1", "F1 (best thr.)"), ("with_self_best_threshold_accuracy", "acc. (best thr.)"),
           ("with_self_best_threshold_recall", "recall"), ("with_self_best_threshold_precision", "precision"),
           ("with_self_roc_auc", "ROC AUC"), ("with_self_f1", "F1 @ thr."), ("f1", "plain F1 @ thr."),
           ("best_threshold_f1", "plain F1 (best thr.)"))


WINDOW_COLUMNS = (("with_self_best_threshold_f1", "F1 (best thr.)"),
                  ("with_self_best_threshold_accuracy", "acc. (best thr.)"), ("with_self_roc_auc", "ROC AUC"),
                  ("f1", "plain F1 @ thr."))
"""The scores averaged over a window of reports (``--window``)."""


def window_scores(history: list[dict], seconds: float) -> dict[str, list[float]]:
    """Per :data:`WINDOW_COLUMNS` key: [mean, sd, number of reports] over the reports of the last
    ``seconds`` of ``history`` (keys no report in the window has are left out)."""
    if not history:
        return {}
    end = max(float(h.get("time", 0.0)) for h in history)
    recent = [h for h in history if float(h.get("time", 0.0)) >= end - seconds]
    out = {}
    for key, _ in WINDOW_COLUMNS:
        values = np.array([h[key] for h in recent if h.get(key) is not None], np.float64)
        if values.size:
            out[key] = [float(values.mean()), float(values.std()), int(values.size)]
    return out


def rescore(run_dir: Path, window_s: float = 0.0, graph: str = "last") -> dict:
    """The scores of the last live graph in ``run_dir/summary.json``, or with ``graph="final"`` of its
    final graph (``causeway final-graph``; ``ValueError`` if it has not the one asked for); with
    ``window_s``, also ``window``: :func:`window_scores` of its history."""
    path = run_dir / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read a run summary ({exc})") from None
    live = summary.get("graph")  # the contract's block; before it, the scores sat at the top level
    scored = summary.get("final_graph") if graph == "final" else (live if isinstance(live, dict) else summary)
    if scored is None:
        raise ValueError(f"{path}: no final graph (run `causeway final-graph --run-dir {run_dir}`)")
    if scored.get("cmi") is None or scored.get("true_graph") is None:
        raise ValueError(f"{path}: no graph with a ground truth to score")
    cmi, truth = np.asarray(scored["cmi"], np.float64), np.asarray(scored["true_graph"], np.uint8)
    if cmi.shape != truth.shape:
        raise ValueError(f"{path}: cmi {cmi.shape} and true_graph {truth.shape} differ in shape")
    scores = score_graph(cmi, truth, float(scored["threshold"]))
    row = {"run": run_dir.name, "env": summary.get("env", ""), "env_steps": int(scored.get("graph_env_steps", 0)),
           **scores}
    if window_s > 0:
        row["window"] = window_scores(summary.get("history") or [], window_s)
    return row


def mean_sd(rows: list[dict]) -> dict[str, tuple[float, float]]:
    """Per scored column: (mean, sample standard deviation) over ``rows`` (sd 0 for one row)."""
    out = {}
    for key, _ in COLUMNS + (("env_steps", ""),):
        values = np.array([row[key] for row in rows], np.float64)
        out[key] = (float(values.mean()), float(values.std(ddof=1)) if len(values) > 1 else 0.0)
    return out


def table(rows: list[dict], mean: bool = False) -> str:
    lines = ["| run | env steps | " + " | ".join(title for _, title in COLUMNS) + " |",
             "|---|---|" + "---|" * len(COLUMNS)]
    for row in rows:
        lines.append(f"| `{row['run']}` | {row['env_steps']:,} | "
                     + " | ".join(f"{row[key]:.3f}" for key, _ in COLUMNS) + " |")
    for env in sorted({row["env"] for row in rows}) if mean else ():
        group = [row for row in rows if row["env"] == env]
        stats = mean_sd(group)
        lines.append(f"| mean ± sd, {len(group)} runs ({env}) | {stats['env_steps'][0]:,.0f} | "
                     + " | ".join(f"{stats[key][0]:.3f} ± {stats[key][1]:.3f}" for key, _ in COLUMNS) + " |")
    for env in sorted({row["env"] for row in rows} & CHAPTER.keys()):
        c = {key: f"{m:.3f} ± {sd:.3f}" for key, (m, sd) in CHAPTER[env].items()}
        lines.append(f"| chapter, Table 3.1 ({env}) | 1.8M | {c['f1']} | {c['accuracy']} | {c['recall']} "
                     f"| {c['precision']} | {c['roc_auc']} | | | |")
    return "\n".join(lines)


def window_table(rows: list[dict], seconds: float, mean: bool = False) -> str:
    """Each run's scores over its last ``seconds`` (mean ± sd over its reports); with ``mean``, the
    mean ± sample sd of those per-run means."""
    lines = [f"| run (reports of the last {seconds:g} s) | reports | "
             + " | ".join(title for _, title in WINDOW_COLUMNS) + " |", "|---|---|" + "---|" * len(WINDOW_COLUMNS)]
    for row in rows:
        w = row.get("window", {})
        count = max((v[2] for v in w.values()), default=0)
        lines.append(f"| `{row['run']}` | {count} | " + " | ".join(
            f"{w[key][0]:.3f} ± {w[key][1]:.3f}" if key in w else "–" for key, _ in WINDOW_COLUMNS) + " |")
    for env in sorted({row["env"] for row in rows}) if mean else ():
        group = [row.get("window", {}) for row in rows if row["env"] == env]
        cells = []
        for key, _ in WINDOW_COLUMNS:
            values = np.array([w[key][0] for w in group if key in w], np.float64)
            cells.append("–" if not values.size else f"{values.mean():.3f} ± "
                         f"{values.std(ddof=1) if values.size > 1 else 0.0:.3f} ({values.size})")
        lines.append(f"| mean ± sd of the runs' means ({env}) | | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=Path("benchmark-results/rescore.json"))
    parser.add_argument("--mean", action="store_true", help="add mean ± sd rows (seeds of one configuration)")
    parser.add_argument("--graph", choices=("last", "final"), default="last",
                        help="score each run's last live report or its final graph (all held-out data)")
    parser.add_argument("--window", type=float, default=0.0, metavar="S",
                        help="also average each run's reports of its last S seconds (0: off)")
    args = parser.parse_args(argv)
    if args.window < 0:
        parser.error("--window must be >= 0")
    rows, failed = [], 0
    for run_dir in args.run_dirs:
        try:
            rows.append(rescore(run_dir, args.window, args.graph))
        except ValueError as exc:
            print(f"skipped: {exc}", file=sys.stderr)
            failed += 1
    if rows:
        print(table(rows, mean=args.mean))
        if args.window > 0:
            print()
            print(window_table(rows, args.window, mean=args.mean))
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1))
        print(f"\nwrote {args.out}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
