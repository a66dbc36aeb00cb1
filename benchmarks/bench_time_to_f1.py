"""(c) Time to reach the paper's causal-graph F1 on Chemical (10 objects), through the real local stack.

Runs ``causeway run`` once per graph with a target F1 and a 15-minute budget, and prints what each
run reached (from its summary.json): wall seconds, env steps, updates, F1 at the working threshold
and at the best threshold (the chapter's Table 3.1 uses the best threshold), accuracy and ROC AUC.

    python -m benchmarks.bench_time_to_f1 [--graphs collider chain full envs/dags/random10.json]
        [--seed 0] [--max-seconds 900] [--metric best_threshold_f1]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

PAPER_F1 = {"collider": 1.000, "chain": 0.996, "full": 0.941}
TARGETS = {"collider": 1.0, "chain": 1.0, "full": 0.95}


def run_one(graph: str, seed: int, max_seconds: float, metric: str, out: Path, extra: list[str]) -> dict:
    name = Path(graph).stem
    run_dir = out / f"{name}-s{seed}"
    target = TARGETS.get(name, 0.95)
    cmd = [sys.executable, "-m", "services.cli", "run", "--graph", graph, "--seed", str(seed),
           "--max-seconds", str(max_seconds), "--target-f1", str(target), "--target-metric", metric,
           "--run-dir", str(run_dir), "--router-port", "0", "--progress", "false", *extra]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return json.loads((run_dir / "summary.json").read_text())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--graphs", nargs="+", default=["collider", "chain", "full", "envs/dags/random10.json"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-seconds", type=float, default=900.0)
    p.add_argument("--metric", default="best_threshold_f1", choices=["f1", "best_threshold_f1"])
    p.add_argument("--out", default=f"runs/bench-f1-{time.strftime('%Y%m%d-%H%M%S')}")
    args, extra = p.parse_known_args()
    rows = [run_one(g, args.seed, args.max_seconds, args.metric, Path(args.out), extra) for g in args.graphs]
    print(f"\n{'graph':12} {'seconds':>8} {'env steps':>10} {'updates':>8} {'F1@0.02':>8} {'best F1':>8} "
          f"{'paper':>6} {'acc':>6} {'AUC':>6}  stopped because")
    for r in rows:
        name = Path(r["env_options"]["graph"]).stem
        paper = f"{PAPER_F1[name]:.3f}" if name in PAPER_F1 else "-"
        print(f"{name:12} {r['wall_seconds']:8.0f} {r['env_steps']:10,} {r['updates']:8,} {r.get('f1', 0):8.3f} "
              f"{r.get('best_threshold_f1', 0):8.3f} {paper:>6} {r.get('accuracy', 0):6.3f} "
              f"{r.get('roc_auc', 0):6.3f}  {r['stopped_because']}")


if __name__ == "__main__":
    main()
