"""Fig. 6.4 (chapter 6): the share of random-skill episodes that induce each interaction, SkiLD vs DIAYN.

For each seed: reward-free pre-training of SkiLD (true local graphs pooled to objects, the chapter's
ablation) and of DIAYN on the same DQN machinery, each for ``--env-steps`` env steps; then
``--episodes`` (500) episodes of random skills per method (a target drawn uniformly from the
history's targets, ``b`` uniform, every L = 20 steps; DIAYN: a uniform skill every 20 steps), and
the same number of episodes of uniformly random primitives for reference. Reported: per
multi-object graph row (an object depending on another object, the interactions Fig. 6.4 shows), the
share of episodes that induce it at least once, mean and standard deviation over seeds, and the
mean over those rows. Then, per SkiLD target, how often 20-step segments of its skill induce it
against uniformly random actions from the same start states (``--target-segments``, 0 to skip):
the low level's own test. One thread; the budget (env steps, updates, wall seconds) is printed.

    python -m benchmarks.skild_coverage [--env installing-printer] [--action-mode primitives|grid] [--env-steps 100000] [--seeds 0 1 2]
        [--episodes 500] [--episode-length 0] [--out runs/skild-coverage] [--graphs true|pcmi]
        [--methods skild diayn random] [--updates-per-step 1] [--eps-decay-steps 40000] [--diversity-weight 0.5] [--relabel-horizon 1] [--n-step 1]
        [--relabel-random 0] [--skill-hidden 128]
        [--target-segments 160]

``--graphs pcmi`` pre-trains SkiLD on the point-wise CMI graphs of a CDL model trained on the run's
own transitions instead of the true ones (the output is then ``<env>-pcmi.json``).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.skild_args import add_learner_arguments, learner_configs
from causal.skild import SkiLDConfig, object_names
from causal.skild_agent import SkillLearnerConfig
from causal.skild_pretrain import PretrainConfig, coverage, describe_row, multi_object, pretrain, target_hit_rates

METHODS = ("skild", "diayn", "random")
TITLES = {"skild": "SkiLD", "diayn": "DIAYN", "random": "random primitives"}


def one_seed(env: str, env_steps: int, episodes: int, episode_length: int, seed: int, graphs: str,
             methods: tuple[str, ...], learner: SkillLearnerConfig, updates_per_step: int,
             cfg: SkiLDConfig = SkiLDConfig(), target_segments: int = 0) -> dict[str, dict]:
    """Coverage per method for one seed: ``{method: {"rows": {(factor, key): share}, "train_cpu_s": ...}}``."""
    out: dict[str, dict] = {}
    run = PretrainConfig(env=env, env_steps=env_steps, episode_length=episode_length, graphs=graphs,
                         updates_per_step=updates_per_step)
    for mode in (m for m in ("skild", "diayn") if m in methods):
        start = time.process_time()
        agent, _ = pretrain(run, cfg, learner, mode=mode, seed=seed)
        trained = time.process_time() - start
        hits: dict[str, int] = {}
        rows = coverage(agent, env, episodes, episode_length, seed=10_000 + seed, skill_steps=agent.cfg.skill_steps,
                        hits=hits)
        out[mode] = {"rows": rows, "train_cpu_s": trained, "updates": agent.updates,
                     "targets": len(agent.history.targets), "target_hits": hits}
        if mode == "skild" and target_segments:
            out[mode]["target_rates"] = target_hit_rates(agent, env, target_segments, seed=20_000 + seed,
                                                         skill_steps=agent.cfg.skill_steps)
        print(f"seed {seed} {mode}: {trained:.0f} CPU s, {agent.updates} updates, "
              f"{len(agent.history.targets)} targets, {hits.get('induced', 0)} of {hits.get('segments', 0)} "
              "random skills induced their target", flush=True)
    if "random" in methods:
        out["random"] = {"rows": coverage(None, env, episodes, episode_length, seed=10_000 + seed)}
    return out


def table(results: list[dict[str, dict]], objects: tuple[str, ...], methods: tuple[str, ...]) -> list[dict]:
    """One line per multi-object row seen by any method: its share per method, mean and std over seeds."""
    width = len(objects) + 1
    keys = sorted({k for r in results for m in methods for k in r[m]["rows"] if multi_object(*k, width)})
    lines = []
    for key in keys:
        line: dict = {"row": describe_row(*key, objects)}
        for m in methods:
            shares = np.array([r[m]["rows"].get(key, 0.0) for r in results])
            line[m] = (float(shares.mean()), float(shares.std()))
        lines.append(line)
    return sorted(lines, key=lambda line: line[methods[-1]][0])


def markdown(lines: list[dict], methods: tuple[str, ...]) -> str:
    head = ("| interaction (object-level row) | " + " | ".join(TITLES[m] for m in methods) + " |\n|---|"
            + "---|" * len(methods) + "\n")
    body = "".join(f"| {line['row']} | " + " | ".join(f"{line[m][0]:.2f} ± {line[m][1]:.2f}" for m in methods)
                   + " |\n" for line in lines)
    mean = {m: np.mean([line[m][0] for line in lines]) if lines else 0.0 for m in methods}
    return head + body + "| **mean over these rows** | " + " | ".join(f"{mean[m]:.2f}" for m in methods) + " |\n"


def target_table(results: list[dict[str, dict]]) -> str:
    """Per target (the union over seeds): the share of skill segments that induce it, the skill
    against uniformly random actions from the same start states, mean over the seeds that have it."""
    per: dict[str, list[tuple[float, float]]] = {}
    for r in results:
        for line in r.get("skild", {}).get("target_rates", []):
            per.setdefault(line["target"], []).append((line["skill"], line["random"]))
    if not per:
        return ""
    head = ("| SkiLD target | seeds | induced by its skill | by random actions, same start states |\n"
            "|---|---|---|---|\n")
    body = "".join(f"| {name} | {len(v)} | {np.mean([a for a, _ in v]):.2f} | {np.mean([b for _, b in v]):.2f} |\n"
                   for name, v in sorted(per.items(), key=lambda kv: -np.mean([b for _, b in kv[1]])))
    return head + body


def main(env: str, env_steps: int, seeds: list[int], episodes: int, episode_length: int, out: Path,
         graphs: str = "true", methods: tuple[str, ...] = METHODS, learner: SkillLearnerConfig = SkillLearnerConfig(),
         updates_per_step: int = 1, cfg: SkiLDConfig = SkiLDConfig(), target_segments: int = 0) -> None:
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    from envs.registry import make_env
    objects = object_names(make_env(env).env_spec().factor_objects)
    wall = time.time()
    methods = tuple(m for m in METHODS if m in methods)
    results = [one_seed(env, env_steps, episodes, episode_length, s, graphs, methods, learner, updates_per_step, cfg,
                        target_segments) for s in seeds]
    lines = table(results, objects, methods)
    text = markdown(lines, methods)
    targets = target_table(results)
    if targets:
        text += "\n" + targets
    budget = {m: {"train_cpu_s": [r[m]["train_cpu_s"] for r in results], "updates": [r[m]["updates"] for r in results],
                  "targets": [r[m]["targets"] for r in results],
                  "target_hits": [r[m]["target_hits"] for r in results],
                  "target_rates": [r[m].get("target_rates", []) for r in results]} for m in methods if m != "random"}
    name = env if graphs == "true" else f"{env}-{graphs}"
    (out / f"{name}.json").write_text(json.dumps({"env": env, "graphs": graphs, "env_steps": env_steps, "seeds": seeds,
                                                 "updates_per_step": updates_per_step,
                                                 "eps_decay_steps": learner.eps_decay_steps, "n_step": learner.n_step,
                                                 "skill_hidden": learner.hidden, "diversity_weight": cfg.diversity_weight,
                                                 "relabel_horizon": cfg.relabel_horizon,
                                                 "relabel_random": cfg.relabel_random,
                                                 "episodes": episodes, "episode_length": episode_length,
                                                 "wall_s": time.time() - wall, "budget": budget, "table": lines},
                                                indent=1))
    (out / f"{name}.md").write_text(text)
    print(text)
    brief = {m: {k: v for k, v in b.items() if k != "target_rates"} for m, b in budget.items()}
    print(f"budget: {env_steps} env steps per method and seed; {brief}; wall {time.time() - wall:.0f} s")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="installing-printer")
    parser.add_argument("--action-mode", choices=("primitives", "grid"), default="primitives",
                        help="grid: the env's cell-by-cell mode (its registry name <env>-grid: left, right, "
                             "forward and the object actions in front) instead of goTo primitives")
    parser.add_argument("--env-steps", type=int, default=100_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--episode-length", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/skild-coverage"))
    parser.add_argument("--graphs", choices=("true", "pcmi"), default="true",
                        help="SkiLD's induced graphs: the true local graphs or a learned model's pCMI")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument("--updates-per-step", type=int, default=1,
                        help="skill-policy updates per batched env step (16 transitions)")
    parser.add_argument("--target-segments", type=int, default=160,
                        help="per SkiLD target, skill segments (and as many of random actions from the same "
                             "start states) run to measure how often each induces it (0: skip)")
    add_learner_arguments(parser)
    args = parser.parse_args()
    if args.action_mode != "primitives" and not args.env.endswith(f"-{args.action_mode}"):
        args.env = f"{args.env}-{args.action_mode}"
    learner, cfg = learner_configs(args, parser)
    main(args.env, args.env_steps, args.seeds, args.episodes, args.episode_length, args.out, args.graphs,
         tuple(args.methods), learner, args.updates_per_step, cfg, args.target_segments)
