"""Chapter 3's generalisation claims on our implementation: CDL vs the dense baselines, ID and OOD.

For every graph and seed: collect uniformly random Chemical transitions, train CDL, Monolithic and
Modular (matched parameters) on the same minibatches, then

- the prediction table of Figs 3.6-3.8: colour accuracy after 1..5 model steps on ID states and on
  OOD states whose positions have noise scale sigma (training: ``position_std`` = 0.01);
- the Match experiment of Figure 3.11: frozen dynamics, a learned reward predictor (CDL: on its
  abstraction + goal factors), CEM planning; episode reward on ID and OOD states.

Prints markdown tables (mean +- std over seeds) and writes JSON and PNGs to ``--out``.

    python -m benchmarks.bench_ch3_generalisation [--graphs collider chain full] [--seeds 0 1 2]
        [--num-objects 10] [--updates 4000] [--transitions 200000] [--noise-scales 0.1 1 10]
        [--match-graphs full] [--match-episodes 32] [--out benchmark-results/ch3]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from causal.factored import FactorLayout
from causal.generalisation import (MODELS, MatchConfig, TrainingConfig, graph_scores, match_returns,
                                   prediction_table, random_transitions, train_dynamics)
from envs.chemical import ChemicalEnv


def log(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", flush=True)


def run_one(graph: str, seed: int, args: argparse.Namespace) -> dict:
    env_kwargs = {"graph": graph, "num_objects": args.num_objects}
    env = ChemicalEnv(**env_kwargs)
    started = time.perf_counter()
    log(f"{graph} seed {seed}: collecting {args.transitions:,} random transitions")
    train, heldout = random_transitions(env_kwargs, args.transitions, seed)
    cfg = TrainingConfig(updates=args.updates)
    trained = train_dynamics(FactorLayout.from_spec(env.env_spec()), train, heldout, cfg, seed,
                             progress=lambda m: log(f"{graph} seed {seed}: {m}"))
    result = {"graph": graph, "seed": seed, "train_transitions": len(train), "updates": args.updates,
              "parameters": trained.parameters(), "train_seconds": trained.seconds,
              "cdl_graph": graph_scores(trained, env.global_graph)}
    log(f"{graph} seed {seed}: CDL graph F1 {result['cdl_graph']['f1']:.3f} "
        f"(best-threshold {result['cdl_graph']['best_threshold_f1']:.3f})")
    result["prediction"] = prediction_table(trained.step_fns(), env_kwargs, args.noise_scales,
                                            args.prediction_starts, 5, seed=1000 + seed,
                                            progress=lambda m: log(f"{graph} seed {seed}: {m}"))
    if graph in args.match_graphs:
        match = MatchConfig(episodes=args.match_episodes)
        result["match"] = match_returns(trained, env_kwargs, args.match_noise_scales, match, seed,
                                        progress=lambda m: log(f"{graph} seed {seed}: {m}"))
    result["seconds"] = round(time.perf_counter() - started, 1)
    return result


def mean_std(values: list[float]) -> str:
    return f"{np.mean(values):.3f} ± {np.std(values):.3f}" if len(values) > 1 else f"{values[0]:.3f}"


def prediction_markdown(results: list[dict]) -> str:
    """One row per (graph, model): 1-step accuracy on ID and each OOD scale, and 5-step on ID."""
    settings = list(results[0]["prediction"]["CDL"])
    head = ["graph", "model", *[f"{s} 1-step" for s in settings], "id 5-step"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for graph in dict.fromkeys(r["graph"] for r in results):
        runs = [r for r in results if r["graph"] == graph]
        for model in MODELS:
            cells = [mean_std([r["prediction"][model][s][0] for r in runs]) for s in settings]
            cells.append(mean_std([r["prediction"][model]["id"][-1] for r in runs]))
            lines.append(f"| {graph} | {model} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def match_markdown(results: list[dict]) -> str:
    runs = [r for r in results if "match" in r]
    if not runs:
        return ""
    settings = list(runs[0]["match"]["CDL"])
    head = ["graph", "planner", *settings]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for graph in dict.fromkeys(r["graph"] for r in runs):
        mine = [r for r in runs if r["graph"] == graph]
        for model in (*MODELS, "Random"):
            cells = [mean_std([float(np.mean(r["match"][model][s])) for r in mine]) for s in settings]
            label = f"CEM + {model}" if model != "Random" else "random actions"
            lines.append(f"| {graph} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(results: list[dict], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for graph in dict.fromkeys(r["graph"] for r in results):
        runs = [r for r in results if r["graph"] == graph]
        settings = list(runs[0]["prediction"]["CDL"])
        fig, axes = plt.subplots(1, len(settings), figsize=(3.6 * len(settings), 3.3), sharey=True, squeeze=False)
        for ax, setting in zip(axes[0], settings):
            for model in MODELS:
                curves = np.array([r["prediction"][model][setting] for r in runs])
                steps = np.arange(1, curves.shape[1] + 1)
                ax.errorbar(steps, curves.mean(0), yerr=curves.std(0), label=model, marker="o", capsize=3)
            ax.set_title("ID" if setting == "id" else f"OOD sigma={setting[4:]}")
            ax.set_xticks(steps)
            ax.set_xlabel("prediction steps")
            ax.set_ylim(0, 1.02)
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel("colour accuracy")
        axes[0][-1].legend(loc="lower right")
        fig.suptitle(f"Chemical {graph}: multi-step prediction (cf. Figs 3.6-3.8)")
        fig.tight_layout()
        path = out / f"prediction_{graph}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append(path)
        if "match" not in runs[0]:
            continue
        settings = list(runs[0]["match"]["CDL"])
        planners = (*MODELS, "Random")
        fig, ax = plt.subplots(figsize=(7, 3.8))
        width = 0.8 / len(settings)
        for k, setting in enumerate(settings):
            means = [np.mean([np.mean(r["match"][p][setting]) for r in runs]) for p in planners]
            errs = [np.std([np.mean(r["match"][p][setting]) for r in runs]) for p in planners]
            ax.bar(np.arange(len(planners)) + k * width, means, width, yerr=errs, capsize=3,
                   label="ID" if setting == "id" else f"OOD sigma={setting[4:]}")
        ax.set_xticks(np.arange(len(planners)) + width * (len(settings) - 1) / 2, planners)
        ax.set_ylabel("episode reward")
        ax.set_title(f"Match on Chemical {graph}: CEM with each model (cf. Figure 3.11)")
        ax.legend()
        ax.grid(alpha=0.3, axis="y")
        fig.tight_layout()
        path = out / f"match_{graph}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append(path)
    return written


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--graphs", nargs="+", default=["collider", "chain", "full"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--num-objects", type=int, default=10)
    p.add_argument("--transitions", type=int, default=200_000)
    p.add_argument("--updates", type=int, default=4000)
    p.add_argument("--noise-scales", nargs="+", type=float, default=[0.1, 1.0, 10.0])
    p.add_argument("--prediction-starts", type=int, default=5000, help="start states per setting (chapter: 5K)")
    p.add_argument("--match-graphs", nargs="*", default=["full"], help="graphs on which to run Match")
    p.add_argument("--match-noise-scales", nargs="+", type=float, default=[1.0])
    p.add_argument("--match-episodes", type=int, default=32)
    p.add_argument("--out", default="benchmark-results/ch3")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for graph in args.graphs:
        for seed in args.seeds:
            results.append(run_one(graph, seed, args))
            (out / "results.json").write_text(json.dumps({"args": vars(args), "results": results}, indent=1))
    tables = "## Prediction (colour accuracy; 1-step unless noted)\n\n" + prediction_markdown(results)
    match = match_markdown(results)
    if match:
        tables += "\n\n## Match (episode reward, 50 steps)\n\n" + match
    (out / "tables.md").write_text(tables + "\n")
    print("\n" + tables)
    for path in plot(results, out):
        print(f"wrote {path}")
    print(f"command: {' '.join([Path(sys.executable).name, '-m', 'benchmarks.bench_ch3_generalisation', *(argv or sys.argv[1:])])}")
    return {"args": vars(args), "results": results}


if __name__ == "__main__":
    main()
