"""Table 5.2 (chapter 5): ablations of ELDEN's local-graph detection (no Mixup & no regulariser,
lambda = 0, a lambda sweep), each a switch of :class:`causal.elden.ELDENConfig`; and Table 5.1's
learned-mask baselines (``input-mask``, ``attention-mask``: :mod:`causal.elden_masks`), each its own
model on ELDEN's network, trained and scored the same way (its graph: the learned mask); and Table
5.1's pCMI row on the same data (``pcmi``: CDL's model, :class:`causal.cdl_trainer.CDLTrainer` at its
defaults, drawing as many transitions as an ELDEN variant: ``updates x members x member_batch /
cdl.batch_size`` updates of 64; its graph: point-wise CMI).

As the chapter does for Tables 5.1-5.2 ("we train the dynamics model of each method ... on
pre-collected transition data"), every variant trains an :class:`~causal.elden_trainer.ELDENTrainer`
in this process on the same pre-collected random-primitive transitions (the stack's collection
policy, :func:`services.env_worker.core.default_policy`), sampling ``members x member_batch`` rows
uniformly per update as the dynamics-learner does, for the same number of updates; then its local
graphs are scored on 50 scripted episodes of unseen seeds exactly as
:mod:`benchmarks.local_graph_table` scores a run's final model (pooled off-diagonal entries, and
per entry). The trained ensembles are kept in ``--out`` beside the results.

    python -m benchmarks.elden_ablation [--envs thawing] [--seeds 0] [--variants no-mixup-no-reg lambda-0 ...]
        [--updates 3000] [--transitions 200000] [--out runs/elden-ablation]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.local_graph_table import BUDGETS, _mean_sd, score_estimators, score_with, scripted_transitions
from causal.cdl import CDLConfig
from causal.cdl_trainer import CDLTrainer
from causal.elden import ELDENConfig
from causal.elden_masks import MaskConfig, MaskTrainer
from causal.elden_trainer import ELDENTrainer
from causal.methods.elden import MASK_ESTIMATORS
from causal.factored import FactorLayout
from envs.registry import EnvOptions, env_entry
from services.env_worker.core import default_policy

VARIANTS: dict[str, dict[str, Any]] = {
    "no-mixup-no-reg": {"mixup": False, "grad_reg": 0.0},
    "no-mixup": {"mixup": False},
    "lambda-0": {"grad_reg": 0.0},
    "lambda-1e-1": {"grad_reg": 1e-1},
    "lambda-1e-2": {"grad_reg": 1e-2},
    "lambda-1e-3": {"grad_reg": 1e-3},
    "lambda-1e-4": {"grad_reg": 1e-4},
    "lambda-1e-5": {"grad_reg": 1e-5},
    "input-mask": {"mixup": False, "grad_reg": 0.0},
    "attention-mask": {"mixup": False, "grad_reg": 0.0},
    "pcmi": {},
}
"""ELDENConfig overrides per variant (the rest: the defaults). ``no-mixup`` keeps the default lambda
(not a row of the chapter's table). The mask baselines use neither ELDEN's regulariser nor its Mixup;
``pcmi`` is not an ELDEN model (CDL's, :data:`PCMI`)."""
PCMI = "pcmi"
"""Table 5.1's pCMI row: CDL's model trained on the same transitions, scored by its point-wise CMI."""
MASK_VARIANTS = {"input-mask": MaskConfig(kind="input"), "attention-mask": MaskConfig(kind="attention")}
"""Table 5.1's learned-mask baselines: their mask (the rest of the model: ELDENConfig's defaults)."""
TABLE_ROWS = {"no-mixup-no-reg": "no Mixup & no Reg", "no-mixup": "no Mixup (lambda default)",
              "lambda-0": "no Reg, i.e. lambda = 0", "lambda-1e-1": "lambda = 1e-1", "lambda-1e-2": "lambda = 1e-2",
              "lambda-1e-3": "lambda = 1e-3", "lambda-1e-4": "lambda = 1e-4", "lambda-1e-5": "lambda = 1e-5",
              "input-mask": "Input Mask (Table 5.1)", "attention-mask": "Attn Mask (Table 5.1)",
              "pcmi": "pCMI (CDL, Table 5.1)"}
CHAPTER = {"thawing": {"no-mixup-no-reg": (0.48, 0.42), "lambda-0": (0.57, 0.52), "lambda-1e-1": (0.68, 0.57),
                       "lambda-1e-2": (0.71, 0.57), "lambda-1e-3": (0.64, 0.55), "lambda-1e-4": (0.65, 0.55),
                       "lambda-1e-5": (0.63, 0.53)},
           "cleaning-car": {"no-mixup-no-reg": (0.44, 0.27), "lambda-0": (0.54, 0.42), "lambda-1e-1": (0.73, 0.58),
                            "lambda-1e-2": (0.76, 0.60), "lambda-1e-3": (0.78, 0.66), "lambda-1e-4": (0.75, 0.60),
                            "lambda-1e-5": (0.72, 0.57)}}
"""Table 5.2 (ROC AUC, F1): Thawing, CarWash; the mask baselines' and pCMI's rows are Table 5.1's."""
for _env, _rows in (("thawing", {"input-mask": (0.50, 0.40), "attention-mask": (0.45, 0.47), "pcmi": (0.55, 0.60)}),
                    ("cleaning-car", {"input-mask": (0.50, 0.32), "attention-mask": (0.47, 0.43),
                                      "pcmi": (0.73, 0.78)})):
    CHAPTER[_env].update(_rows)
CHAPTER["manipulation"] = {"lambda-1e-4": (0.66, 0.25), "pcmi": (0.60, 0.28), "input-mask": (0.50, 0.08),
                           "attention-mask": (0.52, 0.13)}
"""Our stand-in for the chapter's Kitchen: Table 5.1's Kitchen row beside it (ELDEN at Table 5.1's lambda
for Kitchen, 1e-4); Table 5.2 has no Kitchen column."""
DEFAULT_VARIANTS = ["no-mixup-no-reg", "lambda-0", "lambda-1e-1", "lambda-1e-2", "lambda-1e-3"]


def task_kwargs(env: str) -> dict[str, Any]:
    """The env's constructor arguments with the task :data:`BUDGETS` gives it (Table 5.1's task)."""
    flags = BUDGETS[env]
    task = flags[flags.index("--task") + 1] if "--task" in flags else ""
    return env_entry(env).kwargs(EnvOptions(task=task))


def collect(env: str, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, FactorLayout]:
    """(state, action, next_state) of ``steps`` transitions of the stack's collection policy, and the
    env's factor layout."""
    entry = env_entry(env)
    sim = entry.make(**task_kwargs(env))
    policy = default_policy(entry, sim.action_space, seed)
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    obs, _ = sim.reset(seed=seed)
    while len(rows) < steps:
        act = policy.act(obs)
        step_action = int(act[0]) if sim.unwrapped.env_spec().action_kind == "categorical" else act
        nxt, _, terminated, truncated, _ = sim.step(step_action)
        rows.append((obs, np.atleast_1d(act), nxt))
        obs = nxt
        if terminated or truncated:
            obs, _ = sim.reset()
            policy.reset()
    layout = FactorLayout.from_spec(sim.unwrapped.env_spec())
    sim.close()
    state, action, next_state = (np.stack([r[i] for r in rows]).astype(np.float32) for i in range(3))
    return state, action, next_state, layout


def _uniform_updates(trainer: ELDENTrainer | CDLTrainer, tensors: tuple[torch.Tensor, ...], rng: np.random.Generator,
                     steps: int, batch: int, every: int = 0, hook=None, label: str = "") -> dict[str, float]:
    """``steps`` updates of ``trainer``, each on ``batch`` rows drawn uniformly by ``rng``; ``hook()``
    after every ``every``-th update (0: never). The stats of the last update. With ``label``, progress
    on stderr every tenth of the updates (a 3,000-update variant takes minutes to an hour here)."""
    stats: dict[str, float] = {}
    started, tenth = time.perf_counter(), max(steps // 10, 1)
    for step in range(1, steps + 1):
        rows = torch.from_numpy(rng.integers(0, len(tensors[0]), batch))
        stats = trainer.update(*(t[rows] for t in tensors))
        if every and step % every == 0:
            hook()
        if label and (step % tenth == 0 or step == steps):
            print(f"{label}: update {step:,} of {steps:,} ({time.perf_counter() - started:.0f}s)", file=sys.stderr, flush=True)
    return stats


def train(layout: FactorLayout, cfg: ELDENConfig, data: tuple[np.ndarray, ...], updates: int,
          seed: int, mask: MaskConfig | None = None, label: str = "") -> tuple[ELDENTrainer, dict[str, float]]:
    """``updates`` steps of an ELDENTrainer (a MaskTrainer with ``mask``), each on ``members x
    member_batch`` rows drawn uniformly (``label``: progress on stderr)."""
    trainer = ELDENTrainer(layout, cfg, seed=seed) if mask is None else MaskTrainer(layout, cfg, mask, seed=seed)
    tensors = tuple(torch.from_numpy(x) for x in data)
    return trainer, _uniform_updates(trainer, tensors, np.random.default_rng(seed + 1), updates, trainer.batch_size,
                                     label=label)


def train_pcmi(layout: FactorLayout, data: tuple[np.ndarray, ...], updates: int,
               seed: int, label: str = "") -> tuple[CDLTrainer, dict[str, float]]:
    """CDL on the same transitions, drawing as many as ``updates`` ELDEN updates draw (rows uniformly,
    as :func:`train`); the causal term's parents from the CMI of 2,000 rows drawn afresh every 1,000
    updates, as the evaluator would hand them over."""
    elden = ELDENConfig()
    cfg = CDLConfig()
    trainer = CDLTrainer(layout, cfg, seed=seed)
    rng = np.random.default_rng(seed + 1)
    tensors = tuple(torch.from_numpy(x) for x in data)

    def new_parents() -> None:
        sample = torch.from_numpy(rng.integers(0, len(data[0]), 2000))
        trainer.set_parents(trainer.model.cmi(*(t[sample] for t in tensors)).numpy() >= cfg.cmi_threshold)

    steps = -(-updates * elden.members * elden.member_batch // cfg.batch_size)
    return trainer, _uniform_updates(trainer, tensors, rng, steps, cfg.batch_size, every=1000, hook=new_parents,
                                     label=label)


def run_variant(env: str, seed: int, variant: str, data: tuple, layout: FactorLayout, scripted: tuple,
                updates: int) -> tuple[dict[str, Any], ELDENTrainer | CDLTrainer]:
    label = f"{env} seed {seed} {variant}"
    if variant == PCMI:
        started = time.process_time()
        cdl, stats = train_pcmi(layout, data, updates, seed, label)
        return {"env": env, "seed": seed, "variant": variant, "config": {"cdl": dataclasses.asdict(cdl.cfg)},
                "updates": updates, "cdl_updates": cdl.updates, "transitions": int(len(data[0])),
                "final_stats": stats, "train_cpu_s": time.process_time() - started,
                "estimators": score_estimators("cdl", cdl.model, scripted)}, cdl
    cfg = dataclasses.replace(ELDENConfig(), **VARIANTS[variant])
    mask = MASK_VARIANTS.get(variant)
    started = time.process_time()
    trainer, stats = train(layout, cfg, data, updates, seed, mask, label)
    trained = time.process_time() - started
    scored = (score_estimators("elden", trainer.model, scripted) if mask is None
              else score_with({variant: MASK_ESTIMATORS[variant]}, trainer.model, scripted))
    config = VARIANTS[variant] if mask is None else {**VARIANTS[variant], "mask": dataclasses.asdict(mask)}
    return {"env": env, "seed": seed, "variant": variant, "config": config, "updates": updates,
            "transitions": int(len(data[0])), "final_stats": stats, "train_cpu_s": trained,
            "estimators": scored}, trainer


def table(results: list[dict[str, Any]]) -> str:
    """Table 5.2's layout: one row per variant, ROC AUC / PR AUC / best F1 per env beside the chapter's
    (a mask baseline's figures are its mask's, and it has no Attn column)."""
    lines = ["| variant | env | seeds | ROC AUC | PR AUC | best F1 | per entry: ROC AUC / PR AUC / best F1 | "
             "Attn ROC AUC / best F1 | chapter ROC AUC / F1 |", "|---|---|---|---|---|---|---|---|---|"]
    for variant in dict.fromkeys(r["variant"] for r in results):
        for env in dict.fromkeys(r["env"] for r in results if r["variant"] == variant):
            got = [r["estimators"] for r in results if r["variant"] == variant and r["env"] == env]
            own = variant if variant in (*MASK_VARIANTS, PCMI) else "jacobian"
            stat = lambda name, key: _mean_sd([g[name][key] for g in got if name in g])  # noqa: E731
            entry = lambda key: _mean_sd([g[own]["per_entry"][key] for g in got])  # noqa: E731
            chapter = CHAPTER.get(env, {}).get(variant)
            cell = "{:.2f} / {:.2f}".format(*chapter) if chapter else "-"
            lines.append(f"| {TABLE_ROWS[variant]} | {env} | {len(got)} | {stat(own, 'roc_auc')} | "
                         f"{stat(own, 'pr_auc')} | {stat(own, 'best_f1')} | "
                         f"{entry('roc_auc')} / {entry('pr_auc')} / {entry('best_f1')} | "
                         f"{stat('attention', 'roc_auc')} / {stat('attention', 'best_f1')} | {cell} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["thawing"], choices=sorted(CHAPTER))
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS, choices=sorted(VARIANTS))
    p.add_argument("--updates", type=int, default=3000, help="ELDEN updates per variant (Table 5.1's runs: 3,000)")
    p.add_argument("--transitions", type=int, default=200_000,
                   help="pre-collected transitions (the dynamics-learner's replay capacity: 200,000)")
    p.add_argument("--episodes", type=int, default=50, help="scripted evaluation episodes (the chapter: 50)")
    p.add_argument("--out", type=Path, default=Path("runs/elden-ablation"),
                   help="folder of elden-ablation.json (results accumulate there across invocations)")
    args = p.parse_args(argv)
    if args.updates < 1 or args.transitions < 1 or args.episodes < 1:
        p.error("--updates, --transitions and --episodes must be >= 1")
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "elden-ablation.json"
    results = json.loads(path.read_text()) if path.exists() else []
    for env in args.envs:
        scripted = scripted_transitions(env, task_kwargs(env), args.episodes)
        for seed in args.seeds:
            print(f"{env} seed {seed}: collecting {args.transitions:,} transitions", file=sys.stderr, flush=True)
            *data, layout = collect(env, args.transitions, seed)
            for variant in args.variants:
                result, trainer = run_variant(env, seed, variant, tuple(data), layout, scripted, args.updates)
                torch.save(trainer.model.state_dict(), args.out / f"{_name(result)}.pt")
                print(json.dumps(result), flush=True)
                results = [r for r in results if _key(r) != _key(result)] + [result]
                path.write_text(json.dumps(results, indent=1))
    print(table([r for r in results if r["updates"] == args.updates]))


def _name(result: dict[str, Any]) -> str:
    return "{}-s{}-{}-u{}-t{}".format(*_key(result))


def _key(result: dict[str, Any]) -> tuple:
    """Results accumulate in ``--out`` across invocations; a rerun replaces its own entry."""
    return result["env"], result["seed"], result["variant"], result["updates"], result["transitions"]


if __name__ == "__main__":
    main()
