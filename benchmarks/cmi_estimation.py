"""How a trained CDL model's graph scores depend on how CMI is estimated and thresholded (manipulation).

One trained model, one held-out shard, and the choices the graph-evaluator makes around eq. 3.2:

* **samples**: CMI on ``--samples`` transitions drawn from the shard (the evaluator's
  ``eval_samples``; ``--repeats`` draws give the spread) or on the whole shard;
* **constant inputs**: their CMI set to 0, its true value (:meth:`causal.cdl.CDLModel.cmi`), or the
  network's raw estimate;
* **threshold search**: the best-F1 threshold by the exact search (every distinct value) or by the
  200-step grid between the smallest and largest CMI used before.

For each it prints Table 3.1's scores (with-self best-threshold F1 and accuracy, ROC AUC; see
:mod:`causal.graph_metrics`) and the plain F1 at the working threshold, and the noise of a
``--samples`` estimate: the median standard deviation over draws of the true edges' CMI beside their
median CMI, for the weak ones (whole-shard CMI below 0.05 nats).

    python -m benchmarks.cmi_estimation --run-dir runs/manip-ev-s0 [--heldout 40000:4] [--samples 2000]
        [--repeats 5] [--out benchmark-results/cmi-estimation.json]

The shard is collected with the Uniform skill policy and cached as in
:mod:`benchmarks.manipulation_offline` (``--cache``); seed 4 is none of the runs' or that
benchmark's training seeds.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.manipulation_offline import collect_shard, load_shards, parse_shard
from causal.cdl import CDLConfig
from causal.graph_metrics import score_graph
from envs.manipulation_truth import global_graph
from services.supervisor.evaluation import load_model

WEAK = 0.05
"""Nats: true edges whose whole-shard CMI is below this are the weak ones the noise figure is about."""


def table_3_1(cmi: np.ndarray, truth: np.ndarray, grid: bool) -> dict[str, float]:
    """With-self best-threshold F1 / accuracy and ROC AUC (Table 3.1's scoring), plain F1 at 0.02."""
    s = score_graph(cmi, truth, CDLConfig().cmi_threshold, num=200 if grid else None)
    return {"f1": s["with_self_best_threshold_f1"], "accuracy": s["with_self_best_threshold_accuracy"],
            "precision": s["with_self_best_threshold_precision"], "recall": s["with_self_best_threshold_recall"],
            "threshold": s["with_self_best_threshold"], "roc_auc": s["with_self_roc_auc"],
            "plain_f1_at_0.02": s["f1"]}


def estimates(model, data: tuple[torch.Tensor, ...], samples: int, repeats: int, seed: int) -> dict:
    """CMI matrices: the whole shard and ``repeats`` draws of ``samples``, each raw and zeroed."""
    rng = np.random.default_rng(seed)
    draws = [torch.from_numpy(rng.choice(len(data[0]), samples, replace=False)) for _ in range(repeats)]
    out = {}
    for zero in (True, False):
        out[("all", zero)] = [model.cmi(*data, zero_constant_inputs=zero).numpy()]
        out[(samples, zero)] = [model.cmi(*(t[i] for t in data), zero_constant_inputs=zero).numpy() for i in draws]
    return out


def summarise(cmis: dict, truth: np.ndarray) -> list[dict]:
    rows = []
    for (samples, zero), matrices in cmis.items():
        for grid in (False, True):
            scores = [table_3_1(c, truth, grid) for c in matrices]
            row = {"samples": samples, "constant_inputs": "zero" if zero else "raw",
                   "search": "grid" if grid else "exact", "draws": len(matrices)}
            for key in scores[0]:
                values = np.array([s[key] for s in scores])
                row[key] = {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0}
            rows.append(row)
    return rows


def noise(cmis: dict, truth: np.ndarray, samples: int) -> dict[str, float]:
    """Spread of a ``samples``-transition estimate on the weak true edges, against their size."""
    whole = cmis[("all", True)][0]
    draws = np.stack(cmis[(samples, True)])
    off_diagonal = truth.astype(bool) & ~np.eye(*truth.shape, dtype=bool)
    weak = off_diagonal & (np.abs(whole) < WEAK) & (whole != 0)
    return {"weak_true_edges": int(weak.sum()), "median_cmi": float(np.median(whole[weak])),
            "median_std_of_draws": float(np.median(draws.std(axis=0, ddof=1)[weak]))}


def markdown(rows: list[dict], spread: dict[str, float], samples: int) -> str:
    lines = ["| samples | constant inputs | threshold search | F1 (best thr.) | accuracy | precision | recall "
             "| ROC AUC | plain F1 @ 0.02 |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cell = lambda k: f"{r[k]['mean']:.3f}" + (f" ± {r[k]['std']:.3f}" if r["draws"] > 1 else "")
        lines.append(f"| {r['samples']} | {r['constant_inputs']} | {r['search']} | {cell('f1')} | {cell('accuracy')} "
                     f"| {cell('precision')} | {cell('recall')} | {cell('roc_auc')} | {cell('plain_f1_at_0.02')} |")
    lines.append(f"\nWeak true edges (0 < |CMI| < {WEAK} nats on the whole shard): {spread['weak_true_edges']}, "
                 f"median CMI {spread['median_cmi']:.4f} nats; median sd of a {samples}-sample estimate "
                 f"{spread['median_std_of_draws']:.4f} nats.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run-dir", type=Path, required=True, help="a manipulation run with a learner checkpoint")
    p.add_argument("--heldout", type=parse_shard, default=(40000, 4), help="held-out shard STEPS:SEED")
    p.add_argument("--samples", type=int, default=2000, help="transitions per draw (the evaluator's eval_samples)")
    p.add_argument("--repeats", type=int, default=5, help="draws of --samples")
    p.add_argument("--seed", type=int, default=0, help="seed of the draws")
    p.add_argument("--cache", type=Path, default=Path("benchmark-results/manipulation-data"))
    p.add_argument("--out", type=Path, default=Path("benchmark-results/cmi-estimation.json"))
    args = p.parse_args(argv)
    steps, shard_seed = args.heldout
    if not 0 < args.samples < steps or args.repeats < 2:
        p.error("--samples must be positive and below the shard's steps, and --repeats at least 2")
    torch.set_num_threads(1)
    started = time.perf_counter()
    args.cache.mkdir(parents=True, exist_ok=True)
    data = load_shards([collect_shard(args.cache, steps, shard_seed)])
    model, truth = load_model(args.run_dir), global_graph()
    cmis = estimates(model, data, args.samples, args.repeats, args.seed)
    rows, spread = summarise(cmis, truth), noise(cmis, truth, args.samples)
    print(f"{args.run_dir}: model at its last checkpoint, held-out shard {steps:,}:{shard_seed} "
          f"({time.perf_counter() - started:.0f}s)")
    print(markdown(rows, spread, args.samples))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"run_dir": str(args.run_dir), "heldout": [steps, shard_seed],
                                    "rows": rows, "noise": spread}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
