"""CDL update (or CMI) time of ``causal/cdl.py`` (and ``causal/cdl_max.py``) at an earlier git revision against the working tree's, in one run.

The same ``CDLTrainer`` (same parameters, optimiser, batch and seed) runs with the model code of each
revision; timed rounds alternate between the two, so both see the same load, and the median of the
rounds is reported with the ratio before / after. A speed change to the model is measured this way.
``--measure cmi`` times the all-pairs CMI (eq. 3.2) of ``--transitions`` Chemical transitions instead,
and prints the largest difference between the two revisions' CMI; ``--run-dir`` takes a trained
run's model (its checkpointed weights and widths) rather than a fresh one, since which inputs win
the max, and so the cost of the sparse drop-one evaluation, depends on training.

    python -m benchmarks.bench_cdl_revisions --before REV [--objects 10] [--batch 64] [--rounds 7]
        [--updates 5] [--causal-every 1] [--precision fp32|bf16] [--width 64] [--parents true|all] [--measure update|cmi]
        [--transitions 2000] [--run-dir RUN]
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
from benchmarks.bench_cdl_update import chemical_batch, true_parents
from causal.cdl import TRAIN_PRECISIONS, CDLConfig, CDLModel
from causal.cdl_trainer import CDLTrainer
from services.supervisor.evaluation import load_model


def _import_at(revision: str, path: str, name: str, replace: tuple[str, str] | None = None) -> ModuleType:
    """The file ``path`` as it was at ``revision``, imported as module ``name`` (``replace``: one
    substitution in its source first)."""
    source = subprocess.run(["git", "show", f"{revision}:{path}"], check=True, capture_output=True, text=True).stdout
    if replace is not None:
        source = source.replace(*replace)
    file = Path(tempfile.mkdtemp()) / f"{name}.py"
    file.write_text(source)
    spec = importlib.util.spec_from_file_location(name, file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def module_at(revision: str) -> ModuleType:
    """``causal/cdl.py`` as it was at ``revision``, imported under its own name, with the max
    aggregation of ``causal/cdl_max.py`` at the same revision where it has one."""
    replace = None
    if subprocess.run(["git", "cat-file", "-e", f"{revision}:causal/cdl_max.py"], capture_output=True).returncode == 0:
        _import_at(revision, "causal/cdl_max.py", "cdl_max_before")
        replace = ("from causal.cdl_max import", "from cdl_max_before import")
    return _import_at(revision, "causal/cdl.py", "cdl_before", replace)


def time_cmi(models: dict[str, CDLModel], objects: int, transitions: int, rounds: int) -> dict[str, float]:
    """Median seconds of ``model.cmi`` on the same transitions per revision, alternating rounds."""
    _, data = chemical_batch(objects, transitions)
    results = {name: model.cmi(*data) for name, model in models.items()}
    gap = (results["before"] - results["after"]).abs().max().item()
    print(f"  largest |CMI before - CMI after|: {gap:.2e} nats (largest CMI {results['after'].abs().max().item():.3f})")
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(rounds):
        for name, model in models.items():
            t0 = time.perf_counter()
            model.cmi(*data)
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", required=True, help="git revision of the 'before' causal/cdl.py")
    p.add_argument("--objects", type=int, default=10)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--width", type=int, default=64, help="feature hidden = feature dim = head hidden")
    p.add_argument("--causal-every", type=int, default=1)
    p.add_argument("--precision", choices=TRAIN_PRECISIONS, default="fp32", help="the training products' precision")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--updates", type=int, default=5, help="updates per timed round")
    p.add_argument("--measure", choices=["update", "cmi"], default="update")
    p.add_argument("--transitions", type=int, default=2000, help="transitions per CMI (--measure cmi)")
    p.add_argument("--run-dir", type=Path, help="--measure cmi: that run's trained model (Chemical full)")
    p.add_argument("--parents", choices=["true", "all"], default="true",
                   help="the causal term's parents: Chemical full's true graph (a trained run's; default), or every "
                        "input (a fresh trainer's: the causal aggregate is then the full one)")
    args = p.parse_args()
    torch.set_num_threads(1)
    layout, batch = chemical_batch(args.objects, args.batch)
    cfg = CDLConfig(feature_hidden=args.width, feature_dim=args.width, predictor_hidden=args.width,
                    causal_every=args.causal_every, train_precision=args.precision)
    trainers = {}
    for name, module in (("before", module_at(args.before)), ("after", current)):
        trainer = CDLTrainer(layout, cfg, seed=0)
        trainer.model.__class__ = module.CDLModel  # same parameters and buffers, that revision's code
        if args.parents == "true":
            trainer.set_parents(true_parents(args.objects))
        for _ in range(3):
            trainer.update(*batch)
        trainers[name] = trainer
    if args.measure == "cmi":
        measure_cmi(args, {name: trainer.model for name, trainer in trainers.items()})
        return
    times: dict[str, list[float]] = {name: [] for name in trainers}
    cpu: dict[str, list[float]] = {name: [] for name in trainers}
    for _ in range(args.rounds):
        for name, trainer in trainers.items():
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(args.updates):
                trainer.update(*batch)
            times[name].append((time.perf_counter() - t0) / args.updates)
            cpu[name].append((time.process_time() - c0) / args.updates)
    median = {name: statistics.median(t) for name, t in times.items()}
    median_cpu = {name: statistics.median(t) for name, t in cpu.items()}
    print(f"CDLTrainer.update, {args.objects} objects, batch {args.batch}, width {args.width}, causal term every "
          f"{args.causal_every} (parents: {args.parents}), {args.precision} products, 1 thread, median of {args.rounds} alternating rounds of "
          f"{args.updates}; wall-clock and, in brackets, CPU seconds of this process (less disturbed by other load)")
    for name, seconds in median.items():
        print(f"  {name:<6} ({args.before if name == 'before' else 'working tree'}): {seconds * 1000:8.1f} ms/update "
              f"({median_cpu[name] * 1000:.1f} CPU)")
    print(f"  ratio before / after: {median['before'] / median['after']:.2f}x "
          f"({median_cpu['before'] / median_cpu['after']:.2f}x CPU)")


def measure_cmi(args: argparse.Namespace, models: dict[str, CDLModel]) -> None:
    """Print the CMI timing of both revisions, on ``--run-dir``'s trained model when given."""
    if args.run_dir is not None:
        for name, model in models.items():
            trained = load_model(args.run_dir)
            trained.__class__ = type(model)
            models[name] = trained
        args.objects = trained.num_outputs // 3
    median = time_cmi(models, args.objects, args.transitions, args.rounds)
    widths = "trained model of " + str(args.run_dir) if args.run_dir else f"width {args.width}, untrained"
    print(f"CDLModel.cmi, {args.objects} objects, {args.transitions} transitions, {widths}, 1 thread, "
          f"median of {args.rounds} alternating rounds")
    for name, seconds in median.items():
        print(f"  {name:<6} ({args.before if name == 'before' else 'working tree'}): {seconds:8.3f} s/CMI")
    print(f"  ratio before / after: {median['before'] / median['after']:.2f}x")


if __name__ == "__main__":
    main()
