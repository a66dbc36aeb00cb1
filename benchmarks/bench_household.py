"""Household tasks and 2D Minecraft: env steps/s per core, label sparsity, and how far random and
scripted policies get.

    python -m benchmarks.bench_household [--steps 50000] [--seeds 50]

Per environment: steps/s of ``env.step`` under the random-primitive policy (its ``act`` included,
as an env-worker runs it), from a fresh environment so the rule caches warm up inside the
measurement, per second of this process's CPU time, best of three runs (other processes on the
shared cores only slow a run down); the fraction of positive off-diagonal local-graph labels (action column
included) over those steps; the random policy's success rate and mean fraction of stages reached
per episode; the scripted policy's success rate and mean episode length over ``--seeds`` seeds no
test uses.
"""
from __future__ import annotations

import argparse
import time
from typing import Callable

import numpy as np

from envs.household import CleaningCarEnv, InstallingPrinterEnv, ThawingEnv
from envs.household.core import GridTaskEnv
from envs.household.scripted import RandomPrimitivePolicy, ScriptedPolicy, scripted_policy
from envs.minecraft2d import Minecraft2DEnv, Minecraft2DPolicy

ENVS: dict[str, Callable[[], GridTaskEnv]] = {
    "installing-printer": InstallingPrinterEnv,
    "thawing thaw-fish": ThawingEnv,
    "thawing thaw-all": lambda: ThawingEnv(task="thaw-all"),
    "cleaning-car clean-rag (100)": CleaningCarEnv,
    "cleaning-car clean-rag (300)": lambda: CleaningCarEnv(episode_length=300),
    "minecraft2d diamond": Minecraft2DEnv,
}
UNSEEN_SEEDS = 100_000
"""First seed of the scripted-policy evaluation (the tests use seeds below 2000)."""


def step_rate(make: Callable[[], GridTaskEnv], steps: int, repeats: int = 3) -> float:
    """Random-primitive steps per CPU second, with resets, from a fresh environment: the best of
    ``repeats`` runs (other processes on the shared cores only ever slow a run down)."""
    return max(_step_rate(make(), steps) for _ in range(repeats))


def _step_rate(env: GridTaskEnv, steps: int) -> float:
    policy = RandomPrimitivePolicy(env.action_space, seed=0)
    obs, _ = env.reset(seed=0)
    start = time.process_time()
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(int(policy.act(obs)[0]))
        if terminated or truncated:
            obs, _ = env.reset()
    return steps / (time.process_time() - start)


def random_policy_figures(env: GridTaskEnv, steps: int) -> tuple[float, float, float]:
    """(positive off-diagonal label fraction, success rate, mean fraction of stages reached)."""
    policy = RandomPrimitivePolicy(env.action_space, seed=1)
    obs, _ = env.reset(seed=1)
    d = len(env.factor_names)
    positives, successes, stages = 0, [], []
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(int(policy.act(obs)[0]))
        positives += int(info["local_graph"].sum()) - d
        if terminated or truncated:
            successes.append(terminated)
            stages.append(info["num_stages"] / len(env.stage_names))
            obs, _ = env.reset()
    return positives / (steps * d * d), float(np.mean(successes)), float(np.mean(stages))


def scripted_figures(env: GridTaskEnv, policy: ScriptedPolicy, seeds: int) -> tuple[float, float]:
    """(success rate, mean episode length) over ``seeds`` unseen seeds."""
    successes, lengths = [], []
    for seed in range(UNSEEN_SEEDS, UNSEEN_SEEDS + seeds):
        obs, _ = env.reset(seed=seed)
        policy.reset()
        for t in range(1, env.episode_length + 1):
            obs, _, terminated, truncated, _ = env.step(int(policy.act(obs)[0]))
            if terminated or truncated:
                break
        successes.append(terminated)
        lengths.append(t)
    return float(np.mean(successes)), float(np.mean(lengths))


def main(steps: int, seeds: int) -> None:
    print(f"{'environment':30s} {'d_S':>4s} {'|A|':>4s} {'steps/s/core':>12s} {'labels+':>8s} "
          f"{'rand succ':>9s} {'rand stages':>11s} {'script succ':>11s} {'script len':>10s}")
    for name, make in ENVS.items():
        env = make()
        rate = step_rate(make, steps)
        sparsity, rand_success, rand_stages = random_policy_figures(make(), steps)
        policy = Minecraft2DPolicy(env) if isinstance(env, Minecraft2DEnv) else scripted_policy(env)
        success, length = scripted_figures(env, policy, seeds)
        print(f"{name:30s} {len(env.factor_names):4d} {env.action_space.n:4d} {rate:12,.0f} {sparsity:8.2%} "
              f"{rand_success:9.2f} {rand_stages:11.2f} {success:11.2f} {length:10.1f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=50_000, help="random-policy steps per environment")
    parser.add_argument("--seeds", type=int, default=50, help="scripted-policy episodes per environment")
    args = parser.parse_args()
    main(args.steps, args.seeds)
