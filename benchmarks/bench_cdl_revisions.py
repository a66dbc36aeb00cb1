"""CDL update time of ``causal/cdl.py`` at an earlier git revision against the working tree's, in one run.

The same ``CDLTrainer`` (same parameters, optimiser, batch and seed) runs with the model code of each
revision; timed rounds alternate between the two, so both see the same load, and the median of the
rounds is reported with the ratio before / after. A speed change to the model is measured this way.

    python -m benchmarks.bench_cdl_revisions --before REV [--objects 10] [--batch 64] [--rounds 7]
        [--updates 5] [--causal-every 1] [--width 64]
"""
from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import torch

import causal.cdl as current
from benchmarks.bench_cdl_update import chemical_batch
from causal.cdl import CDLConfig
from causal.cdl_trainer import CDLTrainer


def module_at(revision: str) -> ModuleType:
    """``causal/cdl.py`` as it was at ``revision``, imported under its own name."""
    source = subprocess.run(["git", "show", f"{revision}:causal/cdl.py"], check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "cdl_before.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("cdl_before", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["cdl_before"] = module
    spec.loader.exec_module(module)
    return module


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", required=True, help="git revision of the 'before' causal/cdl.py")
    p.add_argument("--objects", type=int, default=10)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--width", type=int, default=64, help="feature hidden = feature dim = head hidden")
    p.add_argument("--causal-every", type=int, default=1)
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--updates", type=int, default=5, help="updates per timed round")
    args = p.parse_args()
    torch.set_num_threads(1)
    layout, batch = chemical_batch(args.objects, args.batch)
    cfg = CDLConfig(feature_hidden=args.width, feature_dim=args.width, predictor_hidden=args.width,
                    causal_every=args.causal_every)
    trainers = {}
    for name, module in (("before", module_at(args.before)), ("after", current)):
        trainer = CDLTrainer(layout, cfg, seed=0)
        trainer.model.__class__ = module.CDLModel  # same parameters and buffers, that revision's code
        for _ in range(3):
            trainer.update(*batch)
        trainers[name] = trainer
    times: dict[str, list[float]] = {name: [] for name in trainers}
    for _ in range(args.rounds):
        for name, trainer in trainers.items():
            t0 = time.perf_counter()
            for _ in range(args.updates):
                trainer.update(*batch)
            times[name].append((time.perf_counter() - t0) / args.updates)
    median = {name: statistics.median(t) for name, t in times.items()}
    print(f"CDLTrainer.update, {args.objects} objects, batch {args.batch}, width {args.width}, causal term every "
          f"{args.causal_every}, 1 thread, median of {args.rounds} alternating rounds of {args.updates}")
    for name, seconds in median.items():
        print(f"  {name:<6} ({args.before if name == 'before' else 'working tree'}): {seconds * 1000:8.1f} ms/update")
    print(f"  ratio before / after: {median['before'] / median['after']:.2f}x")


if __name__ == "__main__":
    main()
