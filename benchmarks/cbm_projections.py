"""Chapter 4's controllable distractors alone: does CBM's CMI give them edges between each other?

A controllable distractor is ``cd_k' = P_k . a`` (``envs.distractors``): its only parent is the action.
With more distractors than action dimensions the state holds redundant copies of the previous action
(any ``action_dim`` of them give every other one). This trains CBM's dynamics on such data alone,
with no scene (so every ``cd <- cd`` edge is spurious, and nothing else can explain one), and prints,
every ``--estimate-every`` updates, the CMI averaged over training as the evaluator averages it:

* ``cd_cd_edges``: off-diagonal ``cd <- cd`` entries at or above the 0.02-nat threshold (of ``k (k - 1)``);
* ``cd_cd_median`` / ``cd_cd_max``: of those entries' CMI;
* ``self_mean`` / ``action_mean``: the mean CMI of each distractor's own value at t and of the action.

``--static`` adds factors that keep a value drawn per episode (``x' = x``: the block scene's
unmovable cube, and its movable cubes in most steps) and ``--uncontrollable`` chapter 4's uniform
distractors; their rows' only true parent is themselves, so every other entry there is spurious too:

* ``static_edges`` / ``static_max``: entries of the static rows at or above the threshold, from any
  input but the row's own factor (of ``static x (d_S)``: the other factors and the action);
* ``ud_edges``: the same for the uncontrollable rows.

Options compare the label (``--target``: changes, the authors' code, or next values, eq. 4.1), eq.
4.5's regulariser (``--l2`` for lambda1 = lambda2), Gaussian noise on the distractors (``--noise``,
which makes them non-deterministic) and the explicit model. Writes ``<out>/projections.json``.

    python -m benchmarks.cbm_projections --target delta
    python -m benchmarks.cbm_projections --target next
    python -m benchmarks.cbm_projections --target delta --noise 0.05
    python -m benchmarks.cbm_projections --target delta --l2 1e-4
    python -m benchmarks.cbm_projections --dynamics explicit --target delta
    python -m benchmarks.cbm_projections --dynamics explicit --target next
    python -m benchmarks.cbm_projections --static 3 --uncontrollable 5 --target next
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from causal.cbm import CBMTrainer
from causal.cbm_config import TARGETS, CBMConfig
from causal.factored import FactorLayout
from envs.distractors import Distractors


def collect(distractors: Distractors, action_dim: int, steps: int, episode_length: int, noise: float,
            rng: np.random.Generator, static: int = 0) -> tuple[torch.Tensor, ...]:
    """``steps`` transitions under uniform random actions, episodes of ``episode_length`` (each starts at
    the distractors' reset values and draws ``static`` values uniformly from [-1, 1], kept through the
    episode, after the distractors); ``noise`` sd of Gaussian noise added to the controllable ones."""
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    state = kept = np.zeros(0)
    for t in range(steps):
        if t % episode_length == 0:
            kept = rng.uniform(-1.0, 1.0, static)
            state = np.concatenate([distractors.reset(rng), kept])
        action = rng.uniform(-1.0, 1.0, action_dim)
        nxt = np.concatenate([distractors.step(action, rng), kept])
        nxt[: distractors.controllable] += noise * rng.standard_normal(distractors.controllable)
        rows.append((state, action, nxt))
        state = nxt
    return tuple(torch.tensor(np.array(column), dtype=torch.float32) for column in zip(*rows))


def scores(cmi: np.ndarray, k: int, threshold: float, uncontrollable: int = 0, static: int = 0) -> dict[str, float]:
    """The ``cd <- cd`` block's off-diagonal entries, the self entries and the action's column; then, for
    the uncontrollable and static rows (after the ``k`` controllable ones, in that order), every entry but
    the row's own factor."""
    between = cmi[:k, :k][~np.eye(k, dtype=bool)]
    out = {"cd_cd_edges": int((between >= threshold).sum()), "of": int(between.size),
           "cd_cd_median": float(np.median(between)), "cd_cd_max": float(between.max()),
           "self_mean": float(np.diag(cmi[:k, :k]).mean()), "action_mean": float(cmi[:k, -1].mean())}
    first_static = k + uncontrollable
    for name, rows in (("ud", range(k, first_static)), ("static", range(first_static, first_static + static))):
        if len(rows):
            others = np.concatenate([np.delete(cmi[j], j) for j in rows])
            out |= {f"{name}_edges": int((others >= threshold).sum()), f"{name}_of": int(others.size),
                    f"{name}_max": float(others.max())}
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--controllable", type=int, default=10, help="controllable distractors")
    p.add_argument("--uncontrollable", type=int, default=0, help="uncontrollable distractors (U(-1, 1) each step)")
    p.add_argument("--static", type=int, default=0, help="factors that keep a per-episode value (x' = x)")
    p.add_argument("--action-dim", type=int, default=4, help="dimensions of the continuous action (block's 4)")
    p.add_argument("--noise", type=float, default=0.0, help="sd of Gaussian noise on the controllable distractors")
    p.add_argument("--steps", type=int, default=10_000, help="transitions (every tenth held out)")
    p.add_argument("--episode-length", type=int, default=100)
    p.add_argument("--updates", type=int, default=3_000)
    p.add_argument("--estimate-every", type=int, default=500)
    p.add_argument("--ema", type=float, default=0.999, help="moving-average weight per update (the evaluator's)")
    p.add_argument("--dynamics", choices=("implicit", "explicit"), default="implicit")
    p.add_argument("--target", choices=TARGETS, default=CBMConfig.target)
    p.add_argument("--l2", type=float, default=CBMConfig.score_l2, help="lambda1 = lambda2 of eq. 4.5")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("benchmark-results/cbm_projections"))
    args = p.parse_args(argv)
    if args.controllable < 2 or args.action_dim < 1 or args.steps < 20 or args.updates < 1 or args.estimate_every < 1 \
            or args.uncontrollable < 0 or args.static < 0:
        p.error("need --controllable >= 2, --action-dim >= 1, --steps >= 20, --updates >= 1, --estimate-every >= 1, "
                "--uncontrollable >= 0, --static >= 0")
    try:  # settings the model would refuse, refused before anything runs
        CBMConfig(dynamics=args.dynamics, target=args.target, score_l2=args.l2, grad_l2=args.l2)
    except ValueError as error:
        p.error(str(error))
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    k, n_ud, c = args.controllable, args.uncontrollable, args.static
    distractors = Distractors(k, n_ud, "continuous", args.action_dim, seed=args.seed)
    state, action, nxt = collect(distractors, args.action_dim, args.steps, args.episode_length, args.noise, rng, c)
    n = k + n_ud + c
    names = (*distractors.names, *(f"static.{i}" for i in range(c)))
    layout = FactorLayout(names=names, kinds=("continuous",) * n, sizes=(1,) * n, locs=(0.0,) * n,
                          scales=(1.0,) * n, action_kind="continuous", action_size=args.action_dim)
    cfg = CBMConfig(dynamics=args.dynamics, target=args.target, score_l2=args.l2, grad_l2=args.l2)
    trainer = CBMTrainer(layout, cfg, seed=args.seed)
    held = np.arange(args.steps) % 10 == 9
    train_rows, held_rows = np.flatnonzero(~held), torch.from_numpy(np.flatnonzero(held))
    generator = torch.Generator().manual_seed(args.seed)
    weight, average, trace = args.ema ** args.estimate_every, None, []
    started = time.perf_counter()
    for u in range(1, args.updates + 1):
        batch = torch.from_numpy(rng.choice(train_rows, cfg.batch_size))
        trainer.update(state[batch], action[batch], nxt[batch])
        if u % args.estimate_every == 0 or u == args.updates:
            new = trainer.model.dynamics_cmi(state[held_rows], action[held_rows], nxt[held_rows], generator).numpy()
            average = new if average is None else weight * average + (1 - weight) * new
            trace.append({"update": u, "seconds": round(time.perf_counter() - started, 1),
                          **scores(average, k, cfg.cmi_threshold, n_ud, c)})
            print(json.dumps(trace[-1]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "projections.json").write_text(json.dumps(
        {"args": vars(args) | {"out": str(args.out)}, "trace": trace, "cmi": average.tolist()}, indent=1))


if __name__ == "__main__":
    main()
