"""CBM's cost (issue 19): one CBM update at N = 64, 128, 512 negatives against one CDL update on the same
factors, and a CMI estimate of each, as ratios measured in the same run.

The variants are timed in interleaved rounds (each round times every variant once, the medians are
compared), so a machine shared with other work slows them alike. Every update is a full training step
(forward, backward, Adam) on the same batch of chemical-distractors transitions; CBM's includes its
reward model, and "CBM explicit" is CDL's model under the same masks plus that reward model. CMI: CDL's
all-pairs estimate (eq. 3.2) and CBM's (eq. 4.3) on the same held-out samples, CBM at 1,024 and 8,192
negatives.

    python -m benchmarks.bench_cbm_update [--num-objects 3] [--distractors 5,5] [--batch 32] [--rounds 15]
"""
from __future__ import annotations

import argparse
import statistics
import time
from typing import Callable

import numpy as np
import torch

from causal.cbm import CBMTrainer
from causal.cbm_config import CBMConfig
from causal.cdl import CDLConfig
from causal.cdl_trainer import CDLTrainer
from causal.factored import FactorLayout
from envs.registry import make_env


def transitions(num_objects: int, distractors: str, rows: int) -> tuple[FactorLayout, tuple[torch.Tensor, ...]]:
    env = make_env("chemical-distractors", graph="full", num_objects=num_objects, distractors=distractors).unwrapped
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    out: list[list] = [[], [], [], []]
    for _ in range(rows):
        action = int(rng.integers(env.action_space.n))
        nxt, reward, *_ = env.step(action)
        for column, value in zip(out, (obs, [action], nxt, reward)):
            column.append(value)
        obs = nxt
    return FactorLayout.from_spec(env.env_spec()), tuple(torch.from_numpy(np.asarray(c, np.float32)) for c in out)


def median_seconds(variants: dict[str, Callable[[], object]], rounds: int, warmup: int = 2) -> dict[str, float]:
    """Median wall time of each variant over ``rounds`` interleaved rounds."""
    for _ in range(warmup):
        for run in variants.values():
            run()
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, run in variants.items():
            started = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - started)
    return {name: statistics.median(t) for name, t in times.items()}


def update_variants(layout: FactorLayout, batch: tuple[torch.Tensor, ...], size: int) -> dict[str, Callable[[], object]]:
    s, a, n, r = (t[:size] for t in batch)
    cdl = CDLTrainer(layout, CDLConfig(batch_size=size))
    out: dict[str, Callable[[], object]] = {"CDL": lambda: cdl.update(s, a, n)}
    for negatives in (64, 128, 512):
        trainer = CBMTrainer(layout, CBMConfig(num_negatives=negatives, batch_size=size))
        out[f"CBM N={negatives}"] = lambda trainer=trainer: trainer.update(s, a, n, r)
    explicit = CBMTrainer(layout, CBMConfig(dynamics="explicit", batch_size=size))
    out["CBM explicit"] = lambda: explicit.update(s, a, n, r)
    return out


def cmi_variants(layout: FactorLayout, batch: tuple[torch.Tensor, ...], samples: int) -> dict[str, Callable[[], object]]:
    s, a, n = (t[-samples:] for t in batch[:3])
    cdl = CDLTrainer(layout, CDLConfig()).model
    cbm = CBMTrainer(layout, CBMConfig()).model
    out: dict[str, Callable[[], object]] = {"CDL": lambda: cdl.cmi(s, a, n)}
    for negatives in (1024, 8192):
        out[f"CBM N={negatives}"] = lambda k=negatives: cbm.dynamics_cmi(s, a, n, num_negatives=k, max_samples=samples)
    return out


def report(title: str, seconds: dict[str, float]) -> None:
    base = seconds["CDL"]
    print(f"\n{title}")
    print("| variant | seconds (median) | x CDL |\n|---|---|---|")
    for name, value in seconds.items():
        print(f"| {name} | {value:.4f} | {value / base:.2f} |")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--num-objects", type=int, default=3)
    p.add_argument("--distractors", default="5,5")
    p.add_argument("--batch", type=int, default=32, help="transitions per update, both methods (CBM's reference: 32)")
    p.add_argument("--rounds", type=int, default=15)
    p.add_argument("--cmi-samples", type=int, default=64)
    p.add_argument("--cmi-rounds", type=int, default=3)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    layout, batch = transitions(args.num_objects, args.distractors, max(args.batch, args.cmi_samples) * 2)
    print(f"chemical-distractors: {args.num_objects} objects, distractors {args.distractors}: "
          f"{layout.num_factors} factors, batch {args.batch}, one thread")
    report("one update (forward, backward, Adam)", median_seconds(update_variants(layout, batch, args.batch), args.rounds))
    report(f"one CMI estimate of every (output, input) pair on {args.cmi_samples} transitions",
           median_seconds(cmi_variants(layout, batch, args.cmi_samples), args.cmi_rounds, warmup=1))


if __name__ == "__main__":
    main()
