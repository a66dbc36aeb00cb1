"""How often the skill collection policy makes the contacts behind manipulation's hard edges, and
what CMI a run learned for them.

The edges *from* ``unm`` and ``rand`` into the robot and ``mov`` exist only while they touch
(``envs/manipulation_truth.local_graph``). This counts, over ``--steps`` steps of the env-worker's
skill policy, the steps whose local graph has such an edge (and the steps holding ``mov``), and,
given a run directory, prints the largest learned CMI of those columns from its ``summary.json``.

    python -m benchmarks.manipulation_contacts [--steps 3000] [--seed 0] [--run-dir runs/manip-long]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from envs.manipulation import ManipulationEnv
from envs.manipulation_layout import EEF, GRP, MOV, RAND, UNM
from envs.manipulation_truth import ACTION
from envs.skills import SkillPolicy

ROWS = np.r_[EEF, GRP, MOV]
SOURCES = {"unm": np.r_[UNM], "rand": np.r_[RAND]}


def contact_fractions(steps: int, seed: int) -> dict[str, float]:
    """Fraction of skill-policy steps with an edge from unm / rand into robot or mov, and holding mov."""
    env = ManipulationEnv()
    policy = SkillPolicy(env.action_space, seed)
    obs, _ = env.reset(seed=seed)
    policy.reset()
    counts = dict.fromkeys((*SOURCES, "holding mov"), 0)
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        graph = info["local_graph"]
        for name, cols in SOURCES.items():
            counts[name] += bool(graph[np.ix_(ROWS, cols)].any())
        counts["holding mov"] += bool(graph[np.r_[MOV], ACTION].any())
        if terminated or truncated:
            obs, _ = env.reset()
            policy.reset()
    return {name: count / steps for name, count in counts.items()}


def learned_cmi(run_dir: Path) -> dict[str, float]:
    """Largest learned CMI (nats) from unm's / rand's x, y columns into robot and mov rows."""
    summary = json.loads((run_dir / "summary.json").read_text())
    cmi, names = np.array(summary["cmi"]), summary["factor_names"]
    out = {}
    for name in SOURCES:
        cols = [i for i, n in enumerate(names) if n.startswith(f"{name}.") and not n.endswith(".z")]
        out[name] = float(cmi[np.ix_(ROWS, cols)].max())
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--run-dir", type=Path, default=None, help="a manipulation run to read learned CMI from")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    started = time.perf_counter()
    fractions = contact_fractions(args.steps, args.seed)
    print(f"skill policy, {args.steps:,} steps, seed {args.seed} ({time.perf_counter() - started:.0f}s):")
    for name, fraction in fractions.items():
        label = name if name == "holding mov" else f"touching {name}"
        print(f"  {label:<14}: {100 * fraction:5.1f}% of steps")
    if args.run_dir is not None:
        for name, value in learned_cmi(args.run_dir).items():
            print(f"  learned CMI, {name} -> robot/mov (max): {value:.4f} nats (threshold 0.02)")


if __name__ == "__main__":
    main()
