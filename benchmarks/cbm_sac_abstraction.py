"""Fig. 4.8 on Chemical with distractors: SAC on CBM's minimal task abstraction vs the full state vs
CDL's abstraction, success in distribution and with distractor values out of range.

The chapter's block scene is not built, so this runs on ``chemical-distractors`` (the Table 4.1
analogue's scene, :mod:`benchmarks.cbm_graph_table`): task ``match-first`` (make object 0's colour its
goal colour), whose reward's parents are a strict subset of the factors. Its true minimal abstraction
is ``{obj0.color, obj0.goal_color}``. The abstractions each policy sees, per seed:

* ``full``: every factor (no abstraction);
* ``cbm``: CBM's minimal abstraction (Theorem 4.1) from its learned implicit dynamics graph and its
  learned reward parents;
* ``cbm_true_reward``: the same learned graph with the true reward parents (Table 4.1's setting; the
  labelled fallback for the learned reward parents);
* ``cdl``: CDL's task-independent abstraction of the graph CDL's (explicit) model learned, with the
  goal colours added: chapter 3 gives Match's goals to the policy as provided extra factors, and CDL's
  abstraction, which never reads the reward, would drop them.

They come from a Table 4.1 run (``--abstractions <out>/cbm_table.json``, the same seeds) or are
learned here briefly (``--model-updates``: random-policy data, then both models, as that benchmark
does). Chemical's actions are discrete, so SAC is the categorical form
(:class:`causal.rl.sac_discrete.DiscreteSACAgent`); the policy and critics read the observation
through the abstraction's binary input mask (:func:`causal.rl.base.abstraction_input_mask`).

Each policy is evaluated (deterministic, ``--eval-episodes`` episodes, the same episode seeds in every
setting) in distribution (``id``), with every distractor value lifted out of its training range [-1, 1]
into [-3, -1] u [1, 3] (``ood_distractors``, the env's ``distractor_ood``), and additionally with the
positions drawn at 100 times their training scale (``ood_all``: every task-irrelevant factor at unseen
values, as the chapter sets them to N(0, 1)). Success: object 0 at its goal colour at the episode's end.

Writes ``<out>/cbm_sac.json``, a markdown table to stdout and ``<out>/cbm_sac.png`` (success vs env
steps per abstraction, and Fig. 4.8's ID / OOD success bars).

    python -m benchmarks.cbm_sac_abstraction --abstractions benchmark-results/cbm_table/cbm_table.json \\
        --seeds 0 1 2 --workers 2 --out benchmark-results/cbm_sac
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
from causal.cbm_config import CBMConfig
from causal.factored import FactorLayout
from causal.rl import ActionSpec, SACConfig, UniformReplay, abstraction_input_mask
from causal.rl.collect import StepCollector
from causal.rl.sac_discrete import DiscreteSACAgent
from envs.registry import make_env

CONDITIONS = ("full", "cbm", "cbm_true_reward", "cdl")
SETTINGS: dict[str, dict[str, Any]] = {
    "id": {},
    "ood_distractors": {"distractor_ood": (1.0, 3.0)},
    "ood_all": {"distractor_ood": (1.0, 3.0), "ood_noise_scale": 1.0},
}
"""Evaluation settings: env kwargs added to the training env's."""
EVAL_SEED = 100_000
"""Evaluation episodes are seeded from here (training episodes from the run's seed)."""


@dataclass(frozen=True)
class SACRun:
    """How long and how one SAC policy trains, and how it is evaluated."""

    steps: int = 5_000
    warmup: int = 500
    hidden: int = 128
    lr: float = 1e-3
    batch_size: int = 128
    init_alpha: float = 0.1
    eval_every: int = 500
    curve_episodes: int = 20
    eval_episodes: int = 100


def scene(args: argparse.Namespace) -> dict[str, Any]:
    """The Table 4.1 analogue's env kwargs (the models' data come from it)."""
    return dict(graph=args.graph, num_objects=args.num_objects, distractors=args.distractors, task=args.task)


def conditions_from_kept(implicit: dict[str, list[int]], explicit: dict[str, list[int]],
                         names: tuple[str, ...] | list[str]) -> dict[str, list[int]]:
    """Kept factors per condition from :func:`benchmarks.cbm_graph_table.abstraction_scores`'s ``kept``
    of the implicit (CBM) and explicit (CDL's model) runs; CDL's gets the goal colours."""
    goals = {j for j, name in enumerate(names) if name.endswith("goal_color")}
    return {"full": list(range(len(names))), "cbm": sorted(implicit["cbm"]),
            "cbm_true_reward": sorted(implicit["cbm_true_reward"]),
            "cdl": sorted(set(explicit["cdl"]) | goals), "true_minimal": sorted(implicit["truth"])}


def abstractions_from_table(path: Path, seed: int, names: tuple[str, ...]) -> dict[str, list[int]]:
    """The kept factors of seed ``seed`` of a :mod:`benchmarks.cbm_graph_table` run."""
    table = json.loads(Path(path).read_text())
    if tuple(table["factor_names"]) != tuple(names):
        raise ValueError(f"{path} was run on other factors: {table['factor_names']}")
    kept = {r["variant"]: r["kept"] for r in table["rows"] if r["seed"] == seed}
    if set(kept) != {"implicit", "explicit"}:
        raise ValueError(f"{path} has no implicit and explicit rows for seed {seed}")
    return conditions_from_kept(kept["implicit"], kept["explicit"], names)


def abstractions_from_training(env_kwargs: dict[str, Any], steps: int, updates: int, seed: int,
                               estimate_every: int = 500) -> dict[str, list[int]]:
    """Both models trained here on ``steps`` random-policy transitions for ``updates`` updates each."""
    from benchmarks.cbm_graph_table import collect, evaluate, train

    spec, data = collect(env_kwargs, steps, seed)
    kept = {}
    for variant in ("implicit", "explicit"):
        # CDL's abstraction comes from CDL's own model, which models changes; CBM's takes its default label
        cfg = CBMConfig(dynamics=variant, target=CBMConfig.target if variant == "implicit" else "delta")
        trained = train(spec, cfg, data, updates, min(estimate_every, updates), 0.999, seed)
        kept[variant] = evaluate(trained, spec, data, seed, ())["kept"]
    return conditions_from_kept(kept["implicit"], kept["explicit"], spec.factor_names)


def make_agent(env_kwargs: dict[str, Any], kept: list[int], run: SACRun, seed: int) -> DiscreteSACAgent:
    """Categorical SAC whose actor and critics see only the factors ``kept``."""
    env = make_env("chemical-distractors", **env_kwargs)
    spec = env.unwrapped.env_spec()
    cfg = SACConfig(hidden=(run.hidden, run.hidden), lr=run.lr, batch_size=run.batch_size, init_alpha=run.init_alpha)
    mask = abstraction_input_mask(FactorLayout.from_spec(spec), kept)
    return DiscreteSACAgent(spec.state_dim, ActionSpec.from_space(env.action_space), cfg, seed, mask)


def evaluate_policy(agent: DiscreteSACAgent, env_kwargs: dict[str, Any], episodes: int,
                    seed: int = EVAL_SEED) -> dict[str, float]:
    """Deterministic episodes ``seed .. seed + episodes - 1``: success rate (the task's objects at their
    goal colours at the end) and mean return."""
    env = make_env("chemical-distractors", **env_kwargs)
    successes, returns = [], []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        total, done, reward = 0.0, False, 0.0
        while not done:
            obs, reward, terminated, truncated, _ = env.step(agent.act(obs, deterministic=True))
            total, done = total + float(reward), terminated or truncated
        successes.append(reward >= 1.0)
        returns.append(total)
    return {"success": float(np.mean(successes)), "return": float(np.mean(returns))}


def train_sac(env_kwargs: dict[str, Any], kept: list[int], run: SACRun,
              seed: int) -> tuple[DiscreteSACAgent, list[dict[str, float]]]:
    """SAC for ``run.steps`` env steps (uniform actions for the first ``run.warmup``, then one update per
    step); the learning curve is the ID success every ``run.eval_every`` steps."""
    agent = make_agent(env_kwargs, kept, run, seed)
    env = make_env("chemical-distractors", **env_kwargs)
    replay = UniformReplay(run.steps, agent.input_mask.obs_dim, 1, seed)
    collector, curve = StepCollector(env, replay, seed), []
    for step in range(1, run.steps + 1):
        collector.step(None if step <= run.warmup else agent)
        if step > run.warmup:
            agent.update(replay.sample(run.batch_size))
        if step % run.eval_every == 0 or step == run.steps:
            curve.append({"env_steps": step, **evaluate_policy(agent, env_kwargs, run.curve_episodes, EVAL_SEED // 2)})
    return agent, curve


def run_condition(job: tuple[dict[str, Any], str, list[int], SACRun, int]) -> dict[str, Any]:
    """One (condition, seed): train, then evaluate in every setting of :data:`SETTINGS`."""
    env_kwargs, condition, kept, run, seed = job
    torch.set_num_threads(1)
    started = time.perf_counter()
    agent, curve = train_sac(env_kwargs, kept, run, seed)
    final = {name: evaluate_policy(agent, {**env_kwargs, **extra}, run.eval_episodes) for name, extra in SETTINGS.items()}
    return {"condition": condition, "seed": seed, "kept": kept, "curve": curve, **final,
            "seconds": time.perf_counter() - started}


def table(rows: list[dict[str, Any]]) -> str:
    """Mean ± sd over seeds per condition, as markdown."""
    lines = ["| abstraction | seeds | factors kept | " + " | ".join(f"{s} success" for s in SETTINGS)
             + " | " + " | ".join(f"{s} return" for s in SETTINGS) + " |", "|---" * (3 + 2 * len(SETTINGS)) + "|"]
    for condition in dict.fromkeys(r["condition"] for r in rows):
        mine = [r for r in rows if r["condition"] == condition]
        cells = [_mean_sd([len(r["kept"]) for r in mine], 1)]
        cells += [_mean_sd([r[s]["success"] for r in mine]) for s in SETTINGS]
        cells += [_mean_sd([r[s]["return"] for r in mine], 2) for s in SETTINGS]
        lines.append(f"| {condition} | {len(mine)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _mean_sd(values: list[float], digits: int = 3) -> str:
    v = np.asarray(values, dtype=float)
    return f"{v.mean():.{digits}f} ± {v.std(ddof=1):.{digits}f}" if len(v) > 1 else f"{v[0]:.{digits}f}"


def plot(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    """Left: ID success vs env steps per condition (mean ± sd over seeds); right: Fig. 4.8's bars."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 3.8))
    for condition in conditions:
        curves = [r["curve"] for r in rows if r["condition"] == condition]
        steps = [p["env_steps"] for p in curves[0]]
        success = np.array([[p["success"] for p in c] for c in curves])
        left.plot(steps, success.mean(0), label=condition)
        left.fill_between(steps, success.mean(0) - success.std(0), success.mean(0) + success.std(0), alpha=0.2)
    left.set(xlabel="env steps", ylabel="ID success rate", ylim=(0, 1.05))
    left.legend(fontsize=8)
    width = 0.8 / len(SETTINGS)
    for k, setting in enumerate(SETTINGS):
        values = [[r[setting]["success"] for r in rows if r["condition"] == c] for c in conditions]
        right.bar(np.arange(len(conditions)) + k * width, [np.mean(v) for v in values], width,
                  yerr=[np.std(v) / max(len(v) ** 0.5, 1) for v in values], label=setting)
    right.set_xticks(np.arange(len(conditions)) + width, conditions, fontsize=8)
    right.set(ylabel="success rate (mean ± s.e.)", ylim=(0, 1.3))
    right.legend(fontsize=8, ncol=len(SETTINGS), loc="upper center")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def jobs(args: argparse.Namespace, run: SACRun) -> list[tuple[dict[str, Any], str, list[int], SACRun, int]]:
    """One job per (seed, condition), the abstractions loaded or learned per seed."""
    names = make_env("chemical-distractors", **scene(args)).unwrapped.factor_names
    out = []
    for seed in args.seeds:
        if args.abstractions is not None:
            kept = abstractions_from_table(args.abstractions, seed, names)
        else:
            kept = abstractions_from_training(scene(args), args.model_steps, args.model_updates, seed)
        print(f"seed {seed} abstractions: {json.dumps(kept)}", flush=True)
        env_kwargs = {**scene(args), "episode_length": args.episode_length}
        out += [(env_kwargs, c, kept[c], run, seed) for c in args.conditions]
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--num-objects", type=int, default=3)
    p.add_argument("--graph", default="full")
    p.add_argument("--distractors", default="5,5")
    p.add_argument("--task", default="match-first")
    p.add_argument("--episode-length", type=int, default=10, help="steps per SAC episode (the models' data: 50)")
    p.add_argument("--abstractions", type=Path, default=None,
                   help="cbm_table.json of a benchmarks.cbm_graph_table run on the same scene; else learn them here")
    p.add_argument("--model-steps", type=int, default=20_000, help="random-policy transitions for the models")
    p.add_argument("--model-updates", type=int, default=2_000, help="updates of each model when learning here")
    for field, default in asdict(SACRun()).items():
        p.add_argument(f"--{field.replace('_', '-')}", type=type(default), default=default)
    p.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--workers", type=int, default=1, help="SAC runs in parallel (one torch thread each)")
    p.add_argument("--out", type=Path, default=Path("benchmark-results/cbm_sac"))
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    run = SACRun(**{f: getattr(args, f) for f in asdict(SACRun())})
    todo, rows = jobs(args, run), []
    meta = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}, "run": asdict(run)}
    with job_pool(args.workers) as pool:
        for row in pool.imap_unordered(run_condition, todo):
            rows.append(row)
            print(f"seed {row['seed']} {row['condition']}: " + json.dumps({s: row[s] for s in SETTINGS})
                  + f" ({row['seconds']:.0f} s)", flush=True)
            (args.out / "cbm_sac.json").write_text(json.dumps({**meta, "rows": rows}, indent=1))
    rows.sort(key=lambda r: (CONDITIONS.index(r["condition"]), r["seed"]))
    plot(rows, args.out / "cbm_sac.png", f"chemical-distractors {args.task}, {args.num_objects} objects, "
         f"distractors {args.distractors}, seeds {args.seeds}")
    print(table(rows))


if __name__ == "__main__":
    main()
