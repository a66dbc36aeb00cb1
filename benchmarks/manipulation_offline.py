"""CDL training settings compared on one fixed manipulation dataset (no services, no collection noise).

A run of the stack mixes what is collected with how the model is trained; this benchmark holds the
data fixed. It collects shards of Uniform-skill transitions (``STEPS:SEED`` each, cached as ``.npz``
under ``--cache`` so a rerun reuses them) plus a held-out shard, then trains CDL (eq. 3.3, the
learner's own :class:`causal.cdl_trainer.CDLTrainer` on uniform minibatches) once per variant and
seed, in parallel processes. Every ``--eval-every`` updates it computes CMI on the held-out shard,
gives the current graph to the causal term (as the evaluator does), and scores it against the
ground truth as the graph-evaluator does (plain and best-threshold F1, ROC AUC, and the EMA-smoothed
CMI's F1). Variants: ``constant`` (``--lr``) and ``cosine`` (``--lr`` to ``--lr-final`` over all
``--updates``, the learner's ``--lr-decay-updates``). Prints one line per evaluation and a table of
the means over the last ``--tail`` evaluations; writes JSON and a plot beside it.

    python -m benchmarks.manipulation_offline [--shards 60000:1 54000:2] [--heldout 6000:3]
        [--variants constant cosine] [--seeds 0 1] [--updates 30000] [--eval-every 3000]
        [--out benchmark-results/manipulation-offline.json]
"""
from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from causal.cdl import CDLConfig
from causal.cdl_trainer import CDLTrainer
from causal.factored import FactorLayout
from causal.graph_metrics import binary_scores, score_graph

VARIANTS = ("constant", "cosine")
SCORES = ("f1", "best_threshold_f1", "roc_auc", "accuracy", "precision", "identifiable_f1", "ema_f1",
          "with_self_best_threshold_f1")
ARRAYS = ("state", "action", "next_state")
CMI_EMA = 0.5
"""Weight of the newest CMI estimate in the smoothed one, per evaluation. The graph-evaluator's
average was this until it became per learner update (0.999 per update, ~0.05 at our 3,000 updates
between evaluations); kept so that the README's offline figures reproduce."""


def parse_shard(text: str) -> tuple[int, int]:
    """``STEPS:SEED`` -> (steps, seed)."""
    try:
        steps, seed = (int(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a shard is STEPS:SEED, got {text!r}") from None
    if steps <= 0:
        raise argparse.ArgumentTypeError(f"a shard needs steps > 0, got {text!r}")
    return steps, seed


def shard_path(cache: Path, steps: int, seed: int) -> Path:
    return cache / f"uniform-{steps}-s{seed}.npz"


def collect_shard(cache: Path, steps: int, seed: int) -> Path:
    """Uniform-skill transitions of the manipulation scene, collected once and cached."""
    path = shard_path(cache, steps, seed)
    if not path.exists():
        from benchmarks.manipulation_contacts import collect

        torch.set_num_threads(1)
        started = time.perf_counter()
        data = collect(steps, seed)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, state=data.state, action=data.action, next_state=data.next_state)
        tmp.replace(path)  # a killed collection leaves no half-written shard behind
        print(f"collected {steps:,} steps, seed {seed} ({time.perf_counter() - started:.0f}s) -> {path}", flush=True)
    return path


def load_shards(paths: list[Path]) -> tuple[torch.Tensor, ...]:
    parts = [np.load(p) for p in paths]
    return tuple(torch.from_numpy(np.concatenate([d[k] for d in parts])) for k in ARRAYS)


def variant_config(name: str, base: CDLConfig, updates: int) -> CDLConfig:
    if name == "constant":
        return replace(base, lr_decay_updates=0)
    if name == "cosine":
        return replace(base, lr_decay_updates=updates)
    raise ValueError(f"unknown variant {name!r} (known: {', '.join(VARIANTS)})")


def train_one(job: dict) -> dict:
    """Train one (variant, seed) on the cached shards; the evaluation curve."""
    from envs.manipulation import ManipulationEnv
    from services.graph_evaluator.core import constant_factor_indices

    torch.set_num_threads(1)
    env = ManipulationEnv()
    spec = env.env_spec()
    env.close()
    truth, constant = np.asarray(spec.global_graph), constant_factor_indices(spec)
    cfg = CDLConfig(**job["cdl"])
    trainer = CDLTrainer(FactorLayout.from_spec(spec), cfg, seed=job["seed"])
    state, action, next_state = load_shards([Path(p) for p in job["train"]])
    held = load_shards([Path(job["heldout"])])
    sampler = torch.Generator().manual_seed(job["seed"])
    curve, ema, started = [], None, time.perf_counter()
    for update in range(1, job["updates"] + 1):
        index = torch.randint(0, len(state), (cfg.batch_size,), generator=sampler)
        trainer.update(state[index], action[index], next_state[index])
        if update % job["eval_every"] and update != job["updates"]:
            continue
        cmi = trainer.model.cmi(*held).numpy()
        ema = cmi if ema is None else CMI_EMA * cmi + (1 - CMI_EMA) * ema
        trainer.set_parents(ema >= cfg.cmi_threshold)
        scores = score_graph(cmi, truth, cfg.cmi_threshold, constant)
        point = {"updates": update, "seconds": round(time.perf_counter() - started, 1), "lr": trainer.lr,
                 **{k: float(scores[k]) for k in SCORES if k in scores},
                 "ema_f1": binary_scores(ema >= cfg.cmi_threshold, truth)["f1"]}
        curve.append(point)
        print(f"  {job['variant']:<8} seed {job['seed']} | {update:>7,} updates | F1 {point['f1']:.3f} "
              f"best {point['best_threshold_f1']:.3f} AUC {point['roc_auc']:.3f} acc {point['accuracy']:.3f} "
              f"(EMA F1 {point['ema_f1']:.3f}) lr {point['lr']:.1e}", flush=True)
    return {"variant": job["variant"], "seed": job["seed"], "curve": curve}


def summarise(runs: list[dict], tail: int) -> list[dict]:
    """Per variant: mean ± sample sd over seeds of each seed's mean over its last ``tail`` evaluations."""
    rows = []
    for name in dict.fromkeys(r["variant"] for r in runs):
        mine = [r for r in runs if r["variant"] == name]
        row = {"variant": name, "seeds": [r["seed"] for r in mine], "updates": mine[0]["curve"][-1]["updates"]}
        for key in SCORES:
            per_seed = np.array([np.mean([p[key] for p in r["curve"][-tail:]]) for r in mine])
            row[key] = {"mean": float(per_seed.mean()),
                        "std": float(per_seed.std(ddof=1)) if len(per_seed) > 1 else 0.0,
                        "per_seed": [float(v) for v in per_seed]}
        rows.append(row)
    return rows


def markdown(rows: list[dict], tail: int) -> str:
    keys = ("f1", "best_threshold_f1", "roc_auc", "accuracy", "identifiable_f1", "with_self_best_threshold_f1")
    head = "| variant | seeds | updates | " + " | ".join(keys) + " |"
    lines = [f"Means of the last {tail} evaluations per seed (mean ± sd over seeds):", head,
             "|" + "---|" * (3 + len(keys))]
    for r in rows:
        cells = [f"{r[k]['mean']:.3f} ± {r[k]['std']:.3f}" for k in keys]
        lines.append(f"| {r['variant']} | {len(r['seeds'])} | {r['updates']:,} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    colours = dict(zip(dict.fromkeys(r["variant"] for r in runs), ("tab:blue", "tab:orange", "tab:green")))
    for r in runs:
        x = [p["updates"] for p in r["curve"]]
        for ax, key in zip(axes, ("f1", "roc_auc", "lr")):
            ax.plot(x, [p[key] for p in r["curve"]], color=colours[r["variant"]], alpha=0.8,
                    label=f"{r['variant']} (seed {r['seed']})")
    for ax, title in zip(axes, ("F1 at 0.02 nats", "ROC AUC of CMI", "learning rate")):
        ax.set_title(title)
        ax.set_xlabel("CDL updates")
        ax.grid(alpha=0.3)
    axes[1].axhline(0.5, color="grey", lw=0.8, ls=":")
    axes[2].set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.suptitle("CDL on a fixed manipulation dataset (Uniform skills)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shards", type=parse_shard, nargs="+", default=[(60000, 1), (54000, 2)],
                   help="training data: STEPS:SEED per shard (collected in parallel, cached)")
    p.add_argument("--heldout", type=parse_shard, default=(6000, 3), help="held-out data for CMI: STEPS:SEED")
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="model init and minibatch seeds")
    p.add_argument("--updates", type=int, default=30000)
    p.add_argument("--eval-every", type=int, default=3000)
    p.add_argument("--tail", type=int, default=3, help="evaluations averaged per seed in the table")
    p.add_argument("--lr", type=float, default=CDLConfig.lr)
    p.add_argument("--lr-final", type=float, default=CDLConfig.lr_final)
    p.add_argument("--feature-dim", type=int, default=CDLConfig.feature_dim)
    p.add_argument("--jobs", type=int, default=2, help="parallel processes")
    p.add_argument("--cache", type=Path, default=Path("benchmark-results/manipulation-data"))
    p.add_argument("--out", type=Path, default=Path("benchmark-results/manipulation-offline.json"))
    args = p.parse_args(argv)
    if args.updates <= 0 or args.eval_every <= 0:
        p.error("--updates and --eval-every must be positive")
    args.cache.mkdir(parents=True, exist_ok=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    base = CDLConfig(lr=args.lr, lr_final=args.lr_final, feature_dim=args.feature_dim, feature_hidden=args.feature_dim)
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        shards = [args.heldout, *args.shards]
        paths = list(pool.map(collect_shard, [args.cache] * len(shards), *zip(*shards)))
        jobs = [{"variant": v, "seed": s, "train": [str(x) for x in paths[1:]], "heldout": str(paths[0]),
                 "updates": args.updates, "eval_every": args.eval_every,
                 "cdl": asdict(variant_config(v, base, args.updates))}
                for v in args.variants for s in args.seeds]
        runs = list(pool.map(train_one, jobs))
    rows = summarise(runs, args.tail)
    table = markdown(rows, args.tail)
    print(table)
    args.out.write_text(json.dumps({"args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                                    "seconds": round(time.perf_counter() - started), "table": rows, "runs": runs},
                                   indent=1))
    plot(runs, args.out.with_suffix(".png"))
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
