"""Fig. 6.5 (chapter 6): downstream task success of a policy over frozen skills, SkiLD vs DIAYN vs PPO.

For each seed: reward-free pre-training of SkiLD (true local graphs pooled to objects) and DIAYN for
``--pretrain-steps`` env steps, then a task policy (PPO over skills, the skills frozen) trained on
the sparse task reward for ``--task-steps`` env steps; PPO from scratch on primitives gets the same
task steps. Reported: the success rate of the episodes finished in each PPO update, mean and
standard deviation over seeds at a few points of training, and the final success (mean over the
last quarter of updates). One thread; budgets (env steps, CPU seconds) are printed.

    python -m benchmarks.skild_downstream [--env installing-printer] [--action-mode primitives|grid] [--task ""] [--pretrain-steps 30000]
        [--task-steps 30000] [--seeds 0 1 2] [--episode-length 0] [--out runs/skild-downstream]
        [--end-on-target] [--updates-per-step 1] [--eps-decay-steps 40000] [--diversity-weight 0.5] [--relabel-horizon 1] [--n-step 1]
        [--relabel-random 0] [--skill-hidden 128]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from causal.skild import SkiLDConfig
from benchmarks.skild_args import add_learner_arguments, learner_configs
from causal.skild_agent import SkillLearnerConfig
from causal.skild_pretrain import PretrainConfig, pretrain
from causal.skild_task import TaskConfig, train_task

METHODS = ("skild", "diayn", "ppo")
TITLES = {"skild": "SkiLD skills", "diayn": "DIAYN skills", "ppo": "PPO from scratch"}


def one_seed(env: str, task: str, pretrain_steps: int, task_steps: int, episode_length: int, seed: int,
             end_on_target: bool = False, learner: SkillLearnerConfig = SkillLearnerConfig(),
             updates_per_step: int = 1, cfg: SkiLDConfig = SkiLDConfig()) -> dict:
    """Success curves per method for one seed, and the CPU seconds spent."""
    out: dict = {}
    tasks = TaskConfig(env_steps=task_steps, end_on_target=end_on_target)
    for mode in METHODS:
        start = time.process_time()
        agent = None
        if mode != "ppo":
            run = PretrainConfig(env=env, env_steps=pretrain_steps, episode_length=episode_length,
                                 updates_per_step=updates_per_step)
            agent, _ = pretrain(run, cfg, learner, mode=mode, seed=seed)
        curve = train_task(agent, env, task, tasks, seed=seed, episode_length=episode_length)
        out[mode] = {"curve": curve, "cpu_s": time.process_time() - start}
        print(f"seed {seed} {mode}: final {final(curve):.2f}, {out[mode]['cpu_s']:.0f} CPU s", flush=True)
    return out


def final(curve: list[tuple[int, float]]) -> float:
    """Mean success over the last quarter of the updates (updates without a finished episode skipped)."""
    tail = [s for _, s in curve[-max(1, len(curve) // 4):] if s == s]
    return float(np.mean(tail)) if tail else 0.0


def at(curve: list[tuple[int, float]], steps: int) -> float:
    """Success of the last update at or before ``steps`` env steps (0 before any episode finished)."""
    before = [s for n, s in curve if n <= steps and s == s]
    return before[-1] if before else 0.0


def markdown(results: list[dict], task_steps: int) -> str:
    points = [task_steps // 4, task_steps // 2, task_steps]
    head = ("| method | " + " | ".join(f"success at {p:,} steps" for p in points)
            + " | final (last quarter) |\n|---|" + "---|" * (len(points) + 1) + "\n")
    lines = []
    for m in METHODS:
        cells = [np.array([at(r[m]["curve"], p) for r in results]) for p in points]
        last = np.array([final(r[m]["curve"]) for r in results])
        lines.append(f"| {TITLES[m]} | " + " | ".join(f"{c.mean():.2f} ± {c.std():.2f}" for c in cells)
                     + f" | {last.mean():.2f} ± {last.std():.2f} |")
    return head + "\n".join(lines) + "\n"


def main(env: str, task: str, pretrain_steps: int, task_steps: int, seeds: list[int], episode_length: int,
         out: Path, end_on_target: bool = False, learner: SkillLearnerConfig = SkillLearnerConfig(),
         updates_per_step: int = 1, cfg: SkiLDConfig = SkiLDConfig()) -> None:
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    wall = time.time()
    results = [one_seed(env, task, pretrain_steps, task_steps, episode_length, s, end_on_target, learner,
                        updates_per_step, cfg) for s in seeds]
    text = markdown(results, task_steps)
    name = (f"{env}-{task}" if task else env) + ("-end-on-target" if end_on_target else "")
    (out / f"{name}.json").write_text(json.dumps({"env": env, "task": task, "pretrain_steps": pretrain_steps,
                                                  "task_steps": task_steps, "seeds": seeds,
                                                  "episode_length": episode_length,
                                                  "end_on_target": end_on_target,
                                                  "updates_per_step": updates_per_step,
                                                  "diversity_weight": cfg.diversity_weight, "relabel_horizon": cfg.relabel_horizon, "relabel_random": cfg.relabel_random,
                                                  "eps_decay_steps": learner.eps_decay_steps, "n_step": learner.n_step, "skill_hidden": learner.hidden, "wall_s": time.time() - wall,
                                                  "results": results}, indent=1))
    (out / f"{name}.md").write_text(text)
    print(text)
    print(f"budget: pre-training {pretrain_steps} env steps, task {task_steps} env steps per method and seed; "
          f"CPU s {[{m: round(r[m]['cpu_s']) for m in METHODS} for r in results]}; wall {time.time() - wall:.0f} s")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="installing-printer")
    parser.add_argument("--action-mode", choices=("primitives", "grid"), default="primitives",
                        help="grid: the env's cell-by-cell mode (its registry name <env>-grid: left, right, "
                             "forward and the object actions in front) instead of goTo primitives")
    parser.add_argument("--task", default="")
    parser.add_argument("--pretrain-steps", type=int, default=30_000)
    parser.add_argument("--task-steps", type=int, default=30_000)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episode-length", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/skild-downstream"))
    parser.add_argument("--end-on-target", action="store_true",
                        help="a SkiLD skill also ends when it induces its target (the chapter: L steps always)")
    parser.add_argument("--updates-per-step", type=int, default=1,
                        help="skill-policy updates per batched env step of pre-training (16 transitions)")
    add_learner_arguments(parser)
    args = parser.parse_args()
    if args.action_mode != "primitives" and not args.env.endswith(f"-{args.action_mode}"):
        args.env = f"{args.env}-{args.action_mode}"
    learner, cfg = learner_configs(args, parser)
    main(args.env, args.task, args.pretrain_steps, args.task_steps, args.seeds, args.episode_length, args.out,
         args.end_on_target, learner, args.updates_per_step, cfg)
