"""Fig. 4.7's DMC curves: SAC on Walker or Cheetah with 20 + 20 distractors, behind each abstraction.

The chapter plots episode reward against training for CBM, CDL, TIA, Denoised MDP, the full state and
the oracle abstraction. Here, each policy is the continuous SAC of :class:`causal.rl.sac.SACAgent`
(CBM's reference settings: [256, 256], lr 1e-4 unless set, tau 0.005, gamma 0.99, batch 256) reading
the observation through a binary input mask (:func:`causal.rl.base.abstraction_input_mask`):

* ``full``: every factor, the 40 distractors included;
* ``true``: the true minimal abstraction of the env's truth (:mod:`envs.dmc`: the scene's factors, no
  distractor): the chapter's "Oracle";
* ``cbm`` and ``cdl``: the abstractions of a Table 4.1 run on the same env and seed
  (``--abstractions <out>/cbm_table.json`` of :mod:`benchmarks.cbm_graph_table`: CBM's minimal
  abstraction from its implicit graph and learned reward parents, CDL's task-independent one from the
  explicit graph), when given.

Uniform actions for ``--warmup`` steps, then one update per env step; every ``--eval-every`` steps
the mean return of ``--eval-episodes`` deterministic episodes (seeded from 100,000, the same for every
condition). TIA and Denoised MDP (pixel-based world models) are not reproduced.

Writes ``<out>/cbm_dmc.json``, a markdown table (final return and the mean over the curve, mean ± sd
over seeds) and ``<out>/cbm_dmc.png`` (return vs env steps per condition).

    python -m benchmarks.cbm_dmc_curve --env dmc-walker --steps 30000 --seeds 0 1 --workers 2 \\
        --out benchmark-results/cbm_dmc
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.pools import job_pool
from causal.abstraction import minimal_abstraction
from causal.factored import FactorLayout
from causal.rl import ActionSpec, SACConfig, UniformReplay, abstraction_input_mask
from causal.rl.collect import StepCollector, evaluate
from causal.rl.sac import SACAgent
from envs.registry import make_env

CONDITIONS = ("full", "true", "cbm", "cdl")
EVAL_SEED = 100_000


@dataclass(frozen=True)
class CurveRun:
    """How long and how one SAC policy trains, and how it is evaluated."""

    steps: int = 30_000
    warmup: int = 2_000
    lr: float = 3e-4
    eval_every: int = 5_000
    eval_episodes: int = 3


def kept_factors(env_name: str, env_kwargs: dict[str, Any], abstractions: Path | None,
                 seed: int) -> dict[str, list[int]]:
    """Factor indices each condition's policy sees: ``full``, ``true`` and, from ``abstractions``, the
    ``cbm`` (implicit) and ``cdl`` (explicit) rows of ``seed``."""
    env = make_env(env_name, **env_kwargs).unwrapped
    spec = env.env_spec()
    kept = {"full": list(range(spec.num_factors)),
            "true": list(minimal_abstraction(spec.global_graph, spec.reward_parents).kept)}
    env.close()
    if abstractions is not None:
        table = json.loads(abstractions.read_text())
        if tuple(table["factor_names"]) != spec.factor_names:
            raise ValueError(f"{abstractions} was learned on other factors than {env_name}'s")
        for row in table["rows"]:
            if row["seed"] == seed and row["variant"] == "implicit":
                kept["cbm"] = row["kept"]["cbm"]
            elif row["seed"] == seed and row["variant"] == "explicit":
                kept["cdl"] = row["kept"]["cdl"]
    return kept


def run_condition(job: tuple[str, dict[str, Any], str, list[int], CurveRun, int]) -> dict[str, Any]:
    """SAC for ``run.steps`` env steps on the factors ``kept``; the learning curve of mean returns."""
    env_name, env_kwargs, condition, kept, run, seed = job
    torch.set_num_threads(1)
    started = time.perf_counter()
    env, probe = make_env(env_name, **env_kwargs), make_env(env_name, **env_kwargs)
    spec = env.unwrapped.env_spec()
    mask = abstraction_input_mask(FactorLayout.from_spec(spec), kept)
    agent = SACAgent(spec.state_dim, ActionSpec.from_space(env.action_space), SACConfig(lr=run.lr), seed, mask)
    replay = UniformReplay(run.steps, spec.state_dim, spec.action_dim, seed)
    collector, curve = StepCollector(env, replay, seed), []
    for step in range(1, run.steps + 1):
        collector.step(None if step <= run.warmup else agent)
        if step > run.warmup:
            agent.update(replay.sample(SACConfig().batch_size))
        if step % run.eval_every == 0 or step == run.steps:
            returns = evaluate(probe, agent, run.eval_episodes, EVAL_SEED)
            curve.append({"env_steps": step, "return": float(np.mean(returns)),
                          "train_return": float(np.mean(collector.episode_returns[-3:] or [0.0]))})
            print(f"  seed {seed} {condition} step {step}: return {curve[-1]['return']:.1f}", flush=True)
    env.close()
    probe.close()
    return {"condition": condition, "seed": seed, "kept": kept, "curve": curve,
            "final_return": curve[-1]["return"], "mean_return": float(np.mean([p["return"] for p in curve])),
            "seconds": time.perf_counter() - started}


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| condition | factors seen | final return | mean return over the curve | seeds |", "|---|---|---|---|---|"]
    for condition in dict.fromkeys(r["condition"] for r in rows):
        mine = [r for r in rows if r["condition"] == condition]
        cells = [f"{np.mean(v):.1f} ± {np.std(v):.1f}" for v in
                 ([r["final_return"] for r in mine], [r["mean_return"] for r in mine])]
        seen = f"{np.mean([len(r['kept']) for r in mine]):.1f}"
        lines.append(f"| {condition} | {seen} | {cells[0]} | {cells[1]} | {len(mine)} |")
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    """Mean return vs env steps per condition (mean ± sd over seeds)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8))
    for condition in dict.fromkeys(r["condition"] for r in rows):
        curves = [r["curve"] for r in rows if r["condition"] == condition]
        steps = [p["env_steps"] for p in curves[0]]
        values = np.array([[p["return"] for p in c] for c in curves])
        ax.plot(steps, values.mean(0), marker="o", label=condition)
        ax.fill_between(steps, values.mean(0) - values.std(0), values.mean(0) + values.std(0), alpha=0.2)
    ax.set(xlabel="env steps", ylabel="episode return (deterministic)")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="dmc-walker", choices=("dmc-walker", "dmc-cheetah"))
    p.add_argument("--task", default="", help="the env's task ('' its default: walk, run)")
    p.add_argument("--distractors", default="20,20")
    p.add_argument("--episode-length", type=int, default=1000)
    p.add_argument("--abstractions", type=Path, default=None,
                   help="cbm_table.json of a benchmarks.cbm_graph_table run on the same env (adds cbm and cdl)")
    p.add_argument("--abstraction-seed", type=int, default=None,
                   help="take every SAC seed's cbm and cdl abstractions from this seed's rows (default: its own)")
    for field, default in asdict(CurveRun()).items():
        p.add_argument(f"--{field.replace('_', '-')}", type=type(default), default=default)
    p.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--workers", type=int, default=1, help="SAC runs in parallel (one torch thread each)")
    p.add_argument("--out", type=Path, default=Path("benchmark-results/cbm_dmc"))
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    run = CurveRun(**{f: getattr(args, f) for f in asdict(CurveRun())})
    env_kwargs = {"distractors": args.distractors, "episode_length": args.episode_length,
                  **({"task": args.task} if args.task else {})}
    todo = []
    for seed in args.seeds:
        source = seed if args.abstraction_seed is None else args.abstraction_seed
        kept = kept_factors(args.env, env_kwargs, args.abstractions, source)
        todo += [(args.env, env_kwargs, c, kept[c], run, seed) for c in args.conditions if c in kept]
    meta = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}, "run": asdict(run)}
    rows: list[dict[str, Any]] = []
    with job_pool(args.workers) as pool:
        for row in pool.imap_unordered(run_condition, todo):
            rows.append(row)
            print(f"seed {row['seed']} {row['condition']}: final {row['final_return']:.1f}, "
                  f"mean {row['mean_return']:.1f} ({row['seconds']:.0f} s)", flush=True)
            (args.out / "cbm_dmc.json").write_text(json.dumps({**meta, "rows": rows}, indent=1))
    rows.sort(key=lambda r: (CONDITIONS.index(r["condition"]), r["seed"]))
    plot(rows, args.out / "cbm_dmc.png", f"{args.env} {args.task or 'default task'}, distractors "
         f"{args.distractors}, seeds {args.seeds}, SAC")
    print(table(rows))


if __name__ == "__main__":
    main()
