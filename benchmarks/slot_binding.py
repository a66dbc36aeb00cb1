"""How many slot updates the factor-extractor needs before its slots bind to objects (issue 24).

The factor-extractor (``services/factor_extractor``) trains Dyn-O's slots (eq. 7.1) for a fixed number of
updates, then freezes them for good, so a budget that stops before slot attention has bound the objects
gives a run whose every later graph is over arbitrary image parts. This benchmark trains exactly what
the extractor trains (:class:`causal.slot_extractor.FrameSlotLearner` with the extractor's default
configuration, one slot per object and the background) on the frames an env-worker sends
(``chemical-pixels``, random actions), for each ``--budgets`` entry (``U``, the mask-drop schedule's
length, is the budget, so a shorter budget is not a prefix of a longer one), and records:

- FG-ARI on ``--eval-frames`` frames of an unseen worker seed, no masks, every ``--log-every`` updates
  (the binding shows as a jump from ~0 to ~0.9 within a few hundred updates);
- at the freeze, the identity head's matching accuracy (:func:`causal.slot_identity.fit_identity` on the
  training frames, the last fifth held out), as the extractor fits it.

Budgets are update counts, so a loaded machine gives the same numbers, only later; one torch thread.
A PNG of FG-ARI against updates (one line per seed and budget) is written next to ``--out``.

    python -m benchmarks.slot_binding --seeds 0 1 2 --budgets 1500 6000 --out benchmark-results/slot-binding/s012.json
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.seeded_table import Record, SaveFn, table_main
from causal.fg_ari import BOUND_FG_ARI, mean_fg_ari
from causal.slot_extractor import FrameSlotLearner
from causal.slot_identity import fit_identity
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.factor_extractor.config import FactorExtractorConfig
from services.runtime.config import build_config

EVAL_SEED_OFFSET = 10_000
"""Evaluation frames come from worker seed ``seed + EVAL_SEED_OFFSET``: unseen in training."""


@dataclasses.dataclass(frozen=True)
class Budget:
    """The frames one seed trains and is scored on (the slot budgets are ``--budgets``)."""

    num_objects: int = 4
    train_frames: int = 4096
    eval_frames: int = 512
    log_every: int = 250
    slot_dim: int = 16
    """d_xi; the extractor's default is 16 (``--method dyno`` and Table 7.1's benchmark use 32)."""


def worker_frames(seed: int, count: int, num_objects: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` frames and label maps as an env-worker of ``seed`` publishes them (random actions)."""
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="chemical-pixels", num_objects=num_objects, graph="full",
                                        batch_steps=512, publish_frames=True, seed=seed))
    frames, labels, held = [], [], 0
    while held < count:
        batch = worker.collect_frames()
        frames.append(batch.frames)
        labels.append(batch.labels)
        held += len(batch.frames)
    return np.concatenate(frames)[:count], np.concatenate(labels)[:count]


def train_budget(seed: int, slot_updates: int, budget: Budget, train: tuple[np.ndarray, np.ndarray],
                 test: tuple[np.ndarray, np.ndarray]) -> Record:
    """The extractor's slot learner trained for ``slot_updates`` on ``train``; its FG-ARI curve and identity."""
    cfg = build_config(FactorExtractorConfig)
    config = dataclasses.replace(cfg.slot, num_slots=budget.num_objects + 1, slot_dim=budget.slot_dim)
    learner = FrameSlotLearner(config, train[0].shape[1], cfg.ae_updates, slot_updates, cfg.ae_lr, seed)
    batches = torch.Generator().manual_seed(seed)
    test_frames = torch.from_numpy(test[0])
    curve: list[tuple[int, float]] = []
    started = time.perf_counter()
    while not learner.frozen:
        idx = torch.randint(len(train[0]), (config.batch_size,), generator=batches).numpy()
        learner.update(torch.from_numpy(train[0][idx]), torch.from_numpy(train[1][idx]))
        slot_updates_done = learner.updates - cfg.ae_updates
        if slot_updates_done > 0 and (slot_updates_done % budget.log_every == 0 or learner.frozen):
            curve.append((slot_updates_done, mean_fg_ari(test[1], learner.segment(test_frames).numpy())))
            print(f"  seed {seed} U {slot_updates}: update {slot_updates_done} FG-ARI {curve[-1][1]:.3f}",
                  file=sys.stderr, flush=True)
    seconds = time.perf_counter() - started
    slots, alpha = learner.encode_with_masks(torch.from_numpy(train[0]))
    _, identity = fit_identity(slots, alpha, torch.from_numpy(train[1]), seed=seed)
    bound_at = next((u for u, score in curve if score >= BOUND_FG_ARI), None)
    return {"slot_updates": slot_updates, "slot_dim": budget.slot_dim, "fg_ari": curve[-1][1], "curve": curve, "bound_at": bound_at,
            "identity_slot_accuracy": identity["slot_accuracy"], "identity_frame_accuracy": identity["frame_accuracy"],
            "train_seconds": seconds}


def run_seed(seed: int, budget: Budget, budgets: list[int], save: SaveFn) -> Record:
    train = worker_frames(seed, budget.train_frames, budget.num_objects)
    test = worker_frames(seed + EVAL_SEED_OFFSET, budget.eval_frames, budget.num_objects)
    out: Record = {"seed": seed, "runs": []}
    for slot_updates in budgets:
        out["runs"].append(train_budget(seed, slot_updates, budget, train, test))
        save(out)
    return out


def table(results: list[Record]) -> str:
    """Markdown: per budget, how many seeds bound, FG-ARI and identity matching (mean +- sd, per seed)."""
    rows = [f"| slot updates | seeds bound (FG-ARI >= {BOUND_FG_ARI}) | FG-ARI at the freeze | per seed "
            f"| first update at FG-ARI >= {BOUND_FG_ARI} | identity: slots / frames matched |", "|---|---|---|---|---|---|"]
    for slot_updates in sorted({r["slot_updates"] for res in results for r in res["runs"]}):
        runs = [r for res in results for r in res["runs"] if r["slot_updates"] == slot_updates]
        scores = [r["fg_ari"] for r in runs]
        bound = [r["bound_at"] for r in runs if r["bound_at"] is not None]
        rows.append(f"| {slot_updates} | {sum(s >= BOUND_FG_ARI for s in scores)} of {len(runs)} "
                    f"| {np.mean(scores):.3f} +- {np.std(scores):.3f} | {', '.join(f'{s:.3f}' for s in scores)} "
                    f"| {', '.join(str(b) for b in bound) or '-'} "
                    f"| {np.mean([r['identity_slot_accuracy'] for r in runs]):.3f} / "
                    f"{np.mean([r['identity_frame_accuracy'] for r in runs]):.3f} |")
    return "\n".join(rows)


def plot(results: list[Record], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for res in results:
        for r in res["runs"]:
            updates, scores = zip(*r["curve"])
            ax.plot(updates, scores, label=f"seed {res['seed']}, U {r['slot_updates']}")
    ax.axhline(BOUND_FG_ARI, color="grey", linestyle=":", linewidth=1)
    ax.set(xlabel="slot updates", ylabel="held-out FG-ARI (no masks)", title="When the extractor's slots bind")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> list[Record]:
    parsed: dict[str, Any] = {}

    def add_arguments(p: argparse.ArgumentParser) -> None:
        p.add_argument("--budgets", nargs="+", type=int, default=[1500, 6000],
                       help="slot-update budgets U to train for, each from the same start")

    def run(seed: int, budget: Budget, args: argparse.Namespace, save: SaveFn) -> Record:
        if min(args.budgets) < 1:
            raise ValueError(f"--budgets must be >= 1, got {args.budgets}")
        parsed["out"] = args.out
        return run_seed(seed, budget, args.budgets, save)

    results = table_main(argv, description=__doc__, budget_type=Budget,
                         default_out=Path("benchmark-results/slot-binding/binding.json"), run_seed=run, table=table,
                         add_arguments=add_arguments)
    if results:
        plot(results, parsed["out"].with_suffix(".png"))
    return results


if __name__ == "__main__":
    main()
