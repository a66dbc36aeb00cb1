"""Table 3.2 on Chemical: the causal graph CDL learns from data collected by different policies.

Runs the real local stack once per collector and seed on Chemical (10 objects, ``full`` graph by
default): ``random`` (uniform actions), ``preddiff`` (PPO on the PredDiff reward, eq. 3.4) and
``curiosity`` (PPO on the causal predictor's error). Every run gets the same env-step budget, the
same throttle and the same ``--updates-per-env-step``: the dynamics-learner trains at that fixed
ratio, and at the budget the env-workers pause until it has caught up, so a collector that is slower
per step no longer buys extra training (the confound of the first comparison). Prints a line per run
and a markdown table, and writes the runs and the table as JSON plus a bar chart beside it.

    python -m benchmarks.bench_collection [--collectors random preddiff curiosity] [--seeds 0 1 2]
        [--max-env-steps 300000] [--updates-per-env-step 0.008] [--steps-per-second 2000]
        [--graph full] [--out benchmark-results/collection.json]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from services.supervisor.config import RunConfig
from services.runtime.config import build_config
from services.supervisor.supervisor import Supervisor

COLLECTORS = {"random": dict(collector="random"),
              "preddiff": dict(collector="ppo", intrinsic="preddiff"),
              "curiosity": dict(collector="ppo", intrinsic="curiosity")}
SCORES = ("f1", "best_threshold_f1", "accuracy", "roc_auc")
PAPER_ACCURACY = {"preddiff": "90.2 ± 0.3", "random": "89.1 ± 0.6", "curiosity": "88.9 ± 0.2"}
"""Table 3.2, accuracy in % (manipulation, 1.8M transitions; not Chemical)."""
RUN_KEYS = ("collector", "seed", "env_steps", "updates", "graph_env_steps", "graph_updates", "wall_seconds",
            "catch_up_seconds", "stopped_because", "restarts", *SCORES)


def run_one(name: str, seed: int, args: argparse.Namespace, root: Path) -> dict:
    """One local-stack run; its summary.json reduced to what the table needs."""
    cfg = build_config(RunConfig, graph=args.graph, num_objects=args.num_objects, seed=seed,
                       max_env_steps=args.max_env_steps, learner_updates_per_env_step=args.updates_per_env_step,
                       worker_max_steps_per_second=args.steps_per_second, max_seconds=args.max_seconds,
                       catch_up_timeout_s=args.catch_up_timeout_s, run_dir=str(root / f"{name}-s{seed}"),
                       router_port=0, metrics_base_port=0, dashboard_port=0, progress=args.progress,
                       evaluate=False, **COLLECTORS[name])  # graph scores only
    summary = Supervisor(cfg).run()
    return {"collector": name, "run_dir": cfg.run_dir, **{k: summary.get(k) for k in RUN_KEYS if k != "collector"}}


def aggregate(runs: list[dict], collectors: list[str]) -> list[dict]:
    """Per collector: means of the counts, mean and sample std of every score."""
    rows = []
    for name in collectors:
        mine = [r for r in runs if r["collector"] == name and r.get("f1") is not None]
        if not mine:
            continue
        row = {"collector": name, "seeds": [r["seed"] for r in mine],
               "env_steps": float(np.mean([r["env_steps"] for r in mine])),
               "updates": float(np.mean([r["updates"] for r in mine]))}
        for key in SCORES:
            values = np.array([r[key] for r in mine], dtype=float)
            row[key] = {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0}
        rows.append(row)
    return rows


def markdown(rows: list[dict]) -> str:
    head = ("| collector | seeds | env steps (mean) | updates (mean) | F1 @ threshold | best-threshold F1 | accuracy "
            "| ROC AUC | paper accuracy % (manipulation) |\n|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        scores = " | ".join(f"{r[k]['mean']:.3f} ± {r[k]['std']:.3f}" for k in SCORES)
        lines.append(f"| {r['collector']} | {' '.join(map(str, r['seeds']))} | {r['env_steps']:,.0f} | "
                     f"{r['updates']:,.0f} | {scores} | {PAPER_ACCURACY.get(r['collector'], '-')} |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / max(len(rows), 1)
    x = np.arange(len(SCORES))
    for i, r in enumerate(rows):
        ax.bar(x + (i - (len(rows) - 1) / 2) * width, [r[k]["mean"] for k in SCORES], width,
               yerr=[r[k]["std"] for k in SCORES], capsize=3, label=f"{r['collector']} (n={len(r['seeds'])})")
    ax.set_xticks(x, ["F1 @ threshold", "best-threshold F1", "accuracy", "ROC AUC"])
    lowest = min((r[k]["mean"] - r[k]["std"] for r in rows for k in SCORES), default=0.0)
    ax.set_ylim(0.5 if lowest > 0.55 else 0.0, 1.0)
    ax.set_ylabel("score (mean ± std over seeds)")
    ax.set_title(title)
    ax.legend(loc="upper left", fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(args: argparse.Namespace) -> None:
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    root = Path(args.run_root or f"runs/bench-collection-{time.strftime('%Y%m%d-%H%M%S')}")
    runs: list[dict] = []
    for seed in args.seeds:
        for name in args.collectors:
            print(f"[{len(runs) + 1}/{len(args.seeds) * len(args.collectors)}] {name} seed {seed}: "
                  f"{args.max_env_steps:,} env steps at {args.updates_per_env_step} updates/step", flush=True)
            r = run_one(name, seed, args, root)
            runs.append(r)
            print(f"    {r['env_steps']:,} env steps, {r['updates']:,} updates (graph from {r['graph_updates']}), "
                  f"{r['wall_seconds']:.0f}s (catch-up {r['catch_up_seconds']:.0f}s): F1 {r.get('f1') or 0:.3f}, "
                  f"best-threshold F1 {r.get('best_threshold_f1') or 0:.3f}, accuracy {r.get('accuracy') or 0:.3f} "
                  f"[{r['stopped_because']}]", flush=True)
            if r["stopped_because"] == "interrupted":
                break
        else:
            continue
        break
    rows = aggregate(runs, args.collectors)
    table = markdown(rows)
    print("\n" + table)
    out.write_text(json.dumps({"config": vars(args), "runs": runs, "table": rows, "markdown": table}, indent=1) + "\n")
    plot(rows, out.with_suffix(".png"), f"Chemical {args.graph}, {args.num_objects} objects: "
                                        f"{args.max_env_steps:,} env steps, {args.updates_per_env_step} updates/step")
    print(f"\nwrote {out} and {out.with_suffix('.png')} (runs in {root})")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--collectors", nargs="+", default=list(COLLECTORS), choices=list(COLLECTORS))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--max-env-steps", type=int, default=300_000)
    p.add_argument("--updates-per-env-step", type=float, default=0.008)
    p.add_argument("--steps-per-second", type=float, default=2000.0, help="throttle per env-worker")
    p.add_argument("--graph", default="full")
    p.add_argument("--num-objects", type=int, default=10)
    p.add_argument("--max-seconds", type=float, default=3600.0, help="hard cap per run (0: none)")
    p.add_argument("--catch-up-timeout-s", type=float, default=600.0)
    p.add_argument("--progress", type=lambda s: s.lower() in ("1", "true", "yes"), default=True,
                   help="the live progress line of each run")
    p.add_argument("--run-root", default="", help="run directories (default runs/bench-collection-<time>)")
    p.add_argument("--out", default="benchmark-results/collection.json")
    return p.parse_args(argv)


if __name__ == "__main__":
    main(parse_args())
