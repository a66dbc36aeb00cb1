"""Can a skill learner learn SkiLD's skills from the data pre-training collected? (issue 23)

One SkiLD pre-training run collects a replay (and its graph history's targets); then each variant of
the low-level learner is trained from scratch on that same replay, offline, for ``--updates``
updates, and each of its skills is run from the same start states as uniformly random actions
(:func:`causal.skild_pretrain.target_hit_rates`). This separates what the learner can learn from
what the collection gave it: every variant sees the same transitions.

Variants (``--variants``):

- ``default``: SkiLD's learner as pre-training runs it (hindsight relabelling of 7/8 of the samples
  to a row their own step induced, K = 4 with the diversity reward, the 128-wide Q-network);
- ``wide``: the same with a 512-wide Q-network;
- ``random``: ``default`` plus half the samples given a target drawn uniformly from the history's
  (``relabel_random`` 0.5), 512 wide;
- ``future-random``: ``random`` with hindsight targets from up to 19 steps later (``relabel_horizon`` 20);
- ``uniform``: every sample labelled with a uniformly drawn target (no hindsight), K = 1, no
  diversity term, 128 wide; ``uniform-wide``: the same, 512 wide;
- ``one-target``: as ``uniform``, but the history holds only ``--target`` (every sample is labelled
  with it): the single-goal learner the others are measured against, on the same data.

    python -m benchmarks.skild_offline_skills [--env installing-printer] [--action-mode grid] [--env-steps 150000]
        [--seed 0] [--updates 9000] [--segments 160] [--variants default wide random future-random uniform uniform-wide one-target]
        [--target "agent, table, action -> agent"] [--out runs/skild-offline-skills]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from causal.skild import SkiLDConfig, graph_matches, object_names, row_keys
from causal.skild_agent import SkillLearnerConfig, SkiLDAgent
from causal.skild_pretrain import PretrainConfig, describe_row, pretrain, target_hit_rates

UNIFORM = {"relabel_fraction": 0.0, "relabel_random": 1.0, "diversity_k": 1, "diversity_weight": 0.0}
"""Every sample labelled with a target drawn uniformly from the history; K = 1, no diversity term."""
VARIANTS: dict[str, tuple[dict, dict]] = {
    "default": ({}, {}),
    "wide": ({}, {"hidden": 512}),
    "random": ({"relabel_random": 0.5}, {"hidden": 512}),
    "future-random": ({"relabel_random": 0.5, "relabel_horizon": 20}, {"hidden": 512}),
    "uniform": (UNIFORM, {}),
    "uniform-wide": (UNIFORM, {"hidden": 512}),
    "one-target": (UNIFORM, {}),  # with a history of --target alone
}


def train_offline(source: SkiLDAgent, cfg: SkiLDConfig, learner: SkillLearnerConfig, updates: int, seed: int,
                  targets: list[tuple[int, int]] | None = None) -> SkiLDAgent:
    """A fresh learner trained for ``updates`` updates on a copy of ``source``'s replay, with its
    history's targets (or only ``targets``)."""
    agent = SkiLDAgent(source.sizes, source.n, source.actions, cfg, learner, mode="skild", seed=seed)
    size = source.replay.size
    agent.replay.capacity, agent.replay.size, agent.replay.next = size, size, 0
    agent.replay.fields = {name: value[:size].copy() for name, value in source.replay.fields.items()}
    agent.replay.fields["b"] %= agent.k
    agent.history.targets = list(source.history.targets if targets is None else targets)
    for _ in range(updates):
        agent.update()
    return agent


def run(env: str, env_steps: int, seed: int, updates: int, segments: int, variants: list[str], target: str,
        out: Path) -> dict:
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    wall = time.time()
    source, envs = pretrain(PretrainConfig(env=env, env_steps=env_steps), SkiLDConfig(), SkillLearnerConfig(), seed=seed)
    objects = object_names(envs.objects)
    factors, rows = source.history.target_arrays(len(objects) + 1)
    keys = row_keys(rows[:, None])[:, 0] if len(rows) else np.zeros(0, np.int64)
    names = [describe_row(int(f), int(k), objects) for f, k in zip(factors, keys)]
    size = source.replay.size
    induced = source.replay.fields["induced"][:size]
    shares = {name: float(graph_matches(induced, np.full(size, f), np.repeat(r[None], size, axis=0)).mean())
              for name, f, r in zip(names, factors, rows)}
    print(f"pre-training: {env_steps} env steps, {size} transitions, {len(names)} targets", flush=True)
    results: dict[str, dict] = {}
    for name in variants:
        skild_kw, learner_kw = VARIANTS[name]
        only = None
        if name == "one-target":
            if target not in names:
                raise SystemExit(f"--target {target!r} is not one of this run's targets: {names}")
            only = [source.history.targets[names.index(target)]]
        start = time.process_time()
        agent = train_offline(source, dataclasses.replace(SkiLDConfig(), **skild_kw),
                              dataclasses.replace(SkillLearnerConfig(), **learner_kw), updates, seed, only)
        cpu = time.process_time() - start
        rates = target_hit_rates(agent, env, segments, seed=20_000 + seed, skill_steps=agent.cfg.skill_steps)
        results[name] = {"skild": skild_kw, "learner": learner_kw, "train_cpu_s": cpu, "rates": rates}
        print(f"{name}: {cpu:.0f} CPU s; " + "; ".join(f"{r['target']} {r['skill']:.2f} (random {r['random']:.2f})"
                                                        for r in rates), flush=True)
    text = markdown(results, names, shares)
    (out / f"{env}-seed{seed}.json").write_text(json.dumps(
        {"env": env, "env_steps": env_steps, "seed": seed, "updates": updates, "segments": segments, "targets": names,
         "replay_shares": shares, "variants": results, "wall_s": time.time() - wall}, indent=1))
    (out / f"{env}-seed{seed}.md").write_text(text)
    print(text)
    print(f"wall {time.time() - wall:.0f} s")
    return results


def markdown(results: dict[str, dict], names: list[str], shares: dict[str, float] | None = None) -> str:
    """One row per target: the share of the replay's transitions that induce it, each variant's share
    of skill segments that induce it, and random actions'."""
    variants = list(results)
    random: dict[str, float] = {}
    for v in sorted(variants, key=lambda v: v != "one-target"):  # other variants' start states win
        random.update({r["target"]: r["random"] for r in results[v]["rates"]})
    shares = shares or {}
    head = ("| target | share of the replay | " + " | ".join(variants) + " | random actions |\n|---|---|"
            + "---|" * (len(variants) + 1) + "\n")
    skill = {v: {r["target"]: r["skill"] for r in results[v]["rates"]} for v in variants}
    body = ""
    for name in names:
        cells = ["" if name not in skill[v] else f"{skill[v][name]:.2f}" for v in variants]
        cells.append(f"{random[name]:.2f}" if name in random else "")
        share = f"{shares[name]:.4f}" if name in shares else ""
        body += f"| {name} | {share} | " + " | ".join(cells) + " |\n"
    return head + body


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="installing-printer")
    parser.add_argument("--action-mode", choices=("primitives", "grid"), default="grid",
                        help="grid: the env's cell-by-cell mode (<env>-grid)")
    parser.add_argument("--env-steps", type=int, default=150_000, help="env steps of the pre-training that collects the replay")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--updates", type=int, default=9_000, help="offline updates per variant")
    parser.add_argument("--segments", type=int, default=160, help="20-step segments per target and policy")
    parser.add_argument("--variants", nargs="+", choices=tuple(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--target", default="agent, table, action -> agent", help="the one-target variant's target")
    parser.add_argument("--out", type=Path, default=Path("runs/skild-offline-skills"))
    args = parser.parse_args()
    if args.action_mode != "primitives" and not args.env.endswith(f"-{args.action_mode}"):
        args.env = f"{args.env}-{args.action_mode}"
    if args.updates < 1 or args.segments < 1 or args.env_steps < 1:
        parser.error("--updates, --segments and --env-steps must be >= 1")
    run(args.env, args.env_steps, args.seed, args.updates, args.segments, args.variants, args.target, args.out)
