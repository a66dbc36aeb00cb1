"""How CDL's cost grows with the number of factors (issue 26): Chemical `full` and a random sparse DAG
with 5, 10, 20 and 40 objects (15 to 120 factors); the random DAG has 2 edges per object.

Per size, in a fresh process (so peak memory is that size's own): seconds per update (batch 64, one
thread), peak resident memory of a learner process (model, Adam state, a 20k-transition replay),
seconds per all-pairs CMI evaluation of 2,000 transitions, seconds of the final graph (CMI on every
held-out transition, 20k here), and the time to a best-threshold F1 of 0.9 of the CMI graph with a
wall-clock budget per size (training in-process on fresh transitions, CMI of 2,000 held-out
transitions every 200 updates). Prints a table, the fitted growth exponents (log-log least squares over the sizes)
and writes a log-log plot; ``--profile`` prints where an update and a CMI evaluation spend their
time at the largest size.

    python -m benchmarks.bench_scale [--sizes 5 10 20 40] [--graphs full random] [--budget 300]
        [--out benchmark-results/scale] [--profile] [--eval 2000] [--heldout 20000] [--device cpu]
        [--precision fp32|bf16] [--seed 0]
    python -m benchmarks.bench_scale --rows ROWS.jsonl [...]   # the table and plot of rows measured earlier

Timings are of this 2-core machine with one torch thread; the exponents, not the seconds, are the
result to carry elsewhere. They are fitted to CPU seconds of the measuring process, which other
processes on a shared machine disturb far less than the wall-clock seconds (printed beside them); the
time to F1 is wall-clock against its budget.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from causal.cdl import TRAIN_PRECISIONS, CDLConfig
from causal.cdl_trainer import CDLTrainer
from causal.factored import FactorLayout
from causal.generalisation import random_transitions
from causal.graph_metrics import score_graph
from envs.chemical import ChemicalEnv
from envs.graphs import random_dag

METRICS = ("update_cpu_s", "cmi_2k_cpu_s", "final_graph_cpu_s", "peak_rss_mb")
"""What the growth exponents are fitted to: CPU seconds of this process (``time.process_time``), which a
shared, loaded machine disturbs far less than wall-clock seconds (also reported, as ``*_s``)."""
TRANSITIONS, HELD_OUT, EVAL = 20_000, 20_000, 2_000


def env_kwargs(graph: str, objects: int) -> dict[str, Any]:
    """Chemical's constructor arguments; ``random`` is a fixed random DAG with 2 edges per object."""
    dag = random_dag(objects, min(2 * objects, objects * (objects - 1) // 2), seed=0) if graph == "random" else graph
    return {"graph": dag, "num_objects": objects}


def make_env(graph: str, objects: int) -> ChemicalEnv:
    return ChemicalEnv(**env_kwargs(graph, objects))


def collect(graph: str, objects: int, count: int, seed: int) -> tuple[tuple[torch.Tensor, ...], ...]:
    """(train, held-out) of ``count`` transitions each, uniformly random actions (Chemical's collection)."""
    train, held = random_transitions(env_kwargs(graph, objects), 2 * count, seed, heldout_fraction=0.5)
    return train.tensors(), held.tensors()


def timed(fn, repeats: int, device: torch.device = torch.device("cpu")) -> tuple[float, float]:
    """Wall-clock and CPU seconds (this process) per call of ``fn`` (a GPU's queue drained at both ends)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    started, cpu = time.perf_counter(), time.process_time()
    for _ in range(repeats):
        fn()
    sync()
    return (time.perf_counter() - started) / repeats, (time.process_time() - cpu) / repeats


def one_size(graph: str, objects: int, budget: float, seed: int = 0, heldout: int = HELD_OUT,
             evaluation: int = EVAL, device: str = "cpu", precision: str = "fp32") -> dict[str, Any]:
    """Every figure of one (graph, size); run in its own process. ``evaluation`` transitions per CMI
    evaluation (2,000 as the evaluator's), ``heldout`` for the final graph (20,000); the model and the
    data on ``device`` (on cuda the wall-clock seconds are the figures, and the GPU's peak memory too);
    ``precision`` the training update's products (``CDLConfig.train_precision``; CMI is fp32 always)."""
    torch.set_num_threads(1)
    where = torch.device(device)
    env = make_env(graph, objects)
    layout = FactorLayout.from_spec(env.env_spec())
    train, held = collect(graph, objects, TRANSITIONS, seed)
    train, held = (tuple(x.to(where) for x in part) for part in (train, tuple(x[:heldout] for x in held)))
    trainer = CDLTrainer(layout, CDLConfig(train_precision=precision), seed=seed)
    trainer.to(where)
    rng = np.random.default_rng(seed)
    draws = 0

    def update() -> None:
        index = torch.from_numpy(rng.integers(0, len(train[0]), 64)).to(where)
        trainer.update(*(x[index] for x in train))

    def fresh(count: int) -> None:
        """New training transitions (as the stack's env-workers stream them), drawn off the clock."""
        nonlocal train, draws
        draws += 1
        new, _ = random_transitions(env_kwargs(graph, objects), count, seed + 1000 * draws, heldout_fraction=0.0)
        train = tuple(x.to(where) for x in new.tensors())

    timed(update, 3, where)  # warm-up
    out: dict[str, Any] = {"graph": graph, "objects": objects, "factors": layout.num_factors, "device": device,
                           "precision": precision, "seed": seed,
                           "parameters": sum(p.numel() for p in trainer.model.parameters()),
                           "cmi_samples": evaluation, "final_samples": len(held[0])}
    sample = tuple(x[:evaluation] for x in held)
    out["update_s"], out["update_cpu_s"] = timed(update, 10, where)
    out["cmi_2k_s"], out["cmi_2k_cpu_s"] = timed(lambda: trainer.model.cmi(*sample), 2, where)
    out["final_graph_s"], out["final_graph_cpu_s"] = timed(lambda: trainer.model.cmi(*held), 1, where)
    out.update(time_to_f1(trainer, update, sample, env.global_graph, budget, fresh=fresh))
    out["fresh_draws"] = draws
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if where.type == "cuda":
        out["peak_gpu_mb"] = torch.cuda.max_memory_allocated(where) / 2**20
    return out


def time_to_f1(trainer: CDLTrainer, update, sample: tuple[torch.Tensor, ...], truth: np.ndarray,
               budget: float, target: float = 0.9, every: int = 200,
               fresh: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Train until the CMI graph's best-threshold F1 reaches ``target`` or ``budget`` seconds of training
    pass. ``fresh(n)``, when given, replaces the training set by ``n`` new transitions after every check
    (``every`` x 64 of them, so each is seen about once, as in the stack's stream), with the clocks
    stopped while it runs. A fixed set does not measure the method past a few epochs: the 20,000
    transitions of the set above, passed ~80 times in 600 s at 10 objects, gave best-threshold F1 0.835
    after 120 s and 0.581 after 600 s (overfitting). ``best_f1_reached`` is the highest F1 of any
    check; ``last_f1`` the last."""
    wall = cpu = 0.0
    best = last = 0.0
    checks = 0
    while wall < budget:
        checks += 1
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(every):
            update()
        cmi = trainer.model.cmi(*sample).cpu().numpy()
        last = score_graph(cmi, truth, trainer.cfg.cmi_threshold)["best_threshold_f1"]
        best = max(best, last)
        trainer.set_parents(cmi >= trainer.cfg.cmi_threshold)
        wall, cpu = wall + time.perf_counter() - t0, cpu + time.process_time() - c0
        if last >= target:
            return {"to_f1_0.9_s": wall, "to_f1_0.9_cpu_s": cpu, "updates_to_f1": trainer.updates,
                    "best_f1_reached": best, "last_f1": last, "checks": checks, "fresh_data": fresh is not None}
        if fresh is not None:
            fresh(every * 64)
    return {"to_f1_0.9_s": None, "updates_to_f1": None, "best_f1_reached": best, "last_f1": last,
            "budget_s": budget, "checks": checks, "fresh_data": fresh is not None}


def exponents(rows: list[dict[str, Any]], key: str) -> float | None:
    """Slope of log(key) on log(factors): the growth exponent."""
    points = [(r["factors"], r[key]) for r in rows if r.get(key)]
    if len(points) < 2:
        return None
    x, y = np.log([p[0] for p in points]), np.log([p[1] for p in points])
    return float(np.polyfit(x, y, 1)[0])


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for graph in dict.fromkeys(r["graph"] for r in rows):
        mine = [r for r in rows if r["graph"] == graph]
        for key, style in (("update_cpu_s", "-o"), ("cmi_2k_cpu_s", "--s"), ("final_graph_cpu_s", ":^")):
            slope = exponents(mine, key)
            ax.loglog([r["factors"] for r in mine], [r[key] for r in mine], style,
                      label=f"{graph}: {key}" + (f" (slope {slope:.2f})" if slope is not None else ""))
    ax.set_xlabel("state factors d_S")
    ax.set_ylabel("CPU seconds (one thread)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def profile(graph: str, objects: int, evaluation: int = EVAL) -> None:
    """Where one update and one CMI evaluation of ``evaluation`` transitions spend their time (torch's
    operator profile)."""
    torch.set_num_threads(1)
    env = make_env(graph, objects)
    trainer = CDLTrainer(FactorLayout.from_spec(env.env_spec()), CDLConfig())
    data = tuple(x[:evaluation] for x in collect(graph, objects, evaluation, 0)[0])
    batch = tuple(x[:64] for x in data)
    trainer.update(*batch)
    from torch.profiler import ProfilerActivity, profile as torch_profile

    for name, fn in (("update", lambda: trainer.update(*batch)), (f"cmi of {len(data[0]):,}", lambda: trainer.model.cmi(*data))):
        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            fn()
        print(f"\n== {name}, {graph} {objects} objects ==")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=10))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", type=int, default=[5, 10, 20, 40])
    p.add_argument("--graphs", nargs="+", default=["full", "random"], choices=["full", "random", "chain", "collider"])
    p.add_argument("--budget", type=float, default=300.0, help="seconds per size for the time to F1 0.9")
    p.add_argument("--out", type=Path, default=Path("benchmark-results/scale"))
    p.add_argument("--profile", action="store_true")
    p.add_argument("--eval", type=int, default=EVAL, help="transitions per CMI evaluation (the s/CMI column and "
                   "the F1 checks); fewer for a quick run on a loaded machine")
    p.add_argument("--heldout", type=int, default=HELD_OUT, help="held-out transitions of the final graph")
    p.add_argument("--device", default="cpu", help="where the model and the data are (cpu, cuda)")
    p.add_argument("--precision", choices=TRAIN_PRECISIONS, default="fp32",
                   help="the training update's matrix products (CDLConfig.train_precision)")
    p.add_argument("--seed", type=int, default=0, help="data, model and time-to-F1 seed")
    p.add_argument("--rows", type=Path, nargs="+", help="report rows measured earlier instead of measuring: "
                   "scale.json files or the JSON lines the measuring prints (say, sizes run one at a time)")
    p.add_argument("--one", nargs=2, metavar=("GRAPH", "OBJECTS"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.one:
        print(json.dumps(one_size(args.one[0], int(args.one[1]), args.budget, seed=args.seed, heldout=args.heldout,
                                  evaluation=args.eval, device=args.device, precision=args.precision)))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    rows = load_rows(args.rows) if args.rows else measure(args)
    report(rows, args.out)
    if args.profile:
        profile(args.graphs[0], max(args.sizes), args.eval)


def measure(args: argparse.Namespace) -> list[dict[str, Any]]:
    """One fresh process per (graph, size), each printing its row."""
    rows = []
    for graph in args.graphs:
        for n in args.sizes:
            result = subprocess.run([sys.executable, "-m", "benchmarks.bench_scale", "--one", graph, str(n),
                                     "--budget", str(args.budget), "--eval", str(args.eval), "--heldout",
                                     str(args.heldout), "--device", args.device, "--precision", args.precision,
                                     "--seed", str(args.seed)],
                                    capture_output=True, text=True, check=True)
            rows.append(json.loads(result.stdout.strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), flush=True)
    return rows


def load_rows(paths: list[Path]) -> list[dict[str, Any]]:
    """Rows from scale.json files (a list) or files of JSON lines, in the order given."""
    rows: list[dict[str, Any]] = []
    for path in paths:
        text = path.read_text().strip()
        rows += json.loads(text) if text.startswith("[") else [json.loads(line) for line in text.splitlines()
                                                               if line.startswith("{")]
    return rows


def report(rows: list[dict[str, Any]], out: Path) -> None:
    """The table, the growth exponents and the plot; rows into ``out/scale.json``."""
    (out / "scale.json").write_text(json.dumps(rows, indent=1))
    print("\nCPU seconds of the process (wall-clock in brackets); the time to F1 is wall-clock, with its budget\n"
          "\n| graph | objects | d_S | parameters | s/update | s/CMI (n) | s final graph (n) "
          "| peak RSS MB | s to best F1 0.9 (updates) | best F1 |\n|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ran = r["to_f1_0.9_s"] or r.get("budget_s")
        reach = (f"{r['to_f1_0.9_s']:.0f} ({r['updates_to_f1']:,})" if r["to_f1_0.9_s"]
                 else f"> {r['budget_s']:.0f} (not reached)" if ran else "not run (budget 0)")
        best = f"{r['best_f1_reached']:.3f}" if ran else "-"
        print(f"| {r['graph']} | {r['objects']} | {r['factors']} | {r['parameters']:,} | "
              f"{r['update_cpu_s']:.3f} ({r['update_s']:.3f}) | {r['cmi_2k_cpu_s']:.2f} ({r['cmi_2k_s']:.2f}; "
              f"{r['cmi_samples']:,}) | {r['final_graph_cpu_s']:.1f} ({r['final_graph_s']:.1f}; {r['final_samples']:,}) | "
              f"{r['peak_rss_mb']:.0f} | {reach} | {best} |")
    for graph in dict.fromkeys(r["graph"] for r in rows):
        mine = [r for r in rows if r["graph"] == graph]
        if len(mine) > 1:
            print(f"{graph}: growth exponents in d_S: " + ", ".join(f"{k} {exponents(mine, k):.2f}" for k in METRICS))
    plot(rows, out / "scale.png")
    print(f"wrote {out / 'scale.json'} and {out / 'scale.png'}")


if __name__ == "__main__":
    main()
