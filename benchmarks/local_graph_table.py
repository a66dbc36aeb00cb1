"""Table 5.1 (chapter 5): how well a method's local graphs match the simulator's, per environment and seed.

For each environment and seed this trains the method through the real local stack (``causeway run``
with an env-step budget and a fixed number of updates per env step, so every seed and env gets the
same training however fast the machine is), then evaluates the run's final model the way chapter 5
does: local graphs predicted for the transitions of 50 episodes of a scripted policy from unseen
seeds, against the simulator's true local graphs (ROC AUC, PR AUC, best F1 over thresholds, pooled
over off-diagonal entries). The run's own held-out score (random-policy transitions, from its
summary) is shown beside it. The manipulation scene stands in for the chapter's Kitchen (its
scripted policy: the Uniform skills).

Every local-graph estimator a method's model supports is evaluated on the same episodes (ELDEN:
its Jacobians and the attention baseline, Table 5.1's "Attn" row), and ``--compare`` prints the
rows of other methods' tables (say, pCMI from ``runs/local-table/cdl-table.json``) beside them.
Method flags per environment (:data:`METHOD_FLAGS`) follow the chapter: ELDEN's rows of Table 5.1
use the best lambda of Table 5.2 per environment.

    python -m benchmarks.local_graph_table [--envs thawing cleaning-car manipulation] [--seeds 0 1 2]
        [--method cdl] [--out runs/local-table] [--reuse] [--episodes 50] [--compare TABLE.json ...]
"""
from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from causal.graph_metrics import score_local_graphs, score_local_graphs_per_entry
from causal.methods import get_method
from envs.registry import env_entry
from services.supervisor.config import load_run_config
from services.supervisor.stop_rules import CATCH_UP_TOLERANCE
from services.supervisor.evaluation import load_model
from services.supervisor.wiring import env_kwargs

BUDGETS: dict[str, list[str]] = {
    "thawing": ["--task", "thaw-fish", "--max-env-steps", "400000", "--learner-updates-per-env-step", "0.025"],
    "cleaning-car": ["--task", "clean-rag", "--max-env-steps", "400000", "--learner-updates-per-env-step", "0.025"],
    "installing-printer": ["--max-env-steps", "200000", "--learner-updates-per-env-step", "0.025"],
    "minecraft2d": ["--task", "diamond", "--max-env-steps", "400000", "--learner-updates-per-env-step", "0.025"],
    "manipulation": ["--max-env-steps", "100000", "--learner-updates-per-env-step", "0.1"],
}
"""Per env: task and budget (10,000 updates each; 400k steps take ~10 minutes on a household env here).
The run waits up to 2 hours for the learner to make its share of updates, so a loaded machine still
gives every seed the same training."""
METHOD_FLAGS: dict[str, dict[str, list[str]]] = {
    "elden": {"thawing": ["--elden-grad-reg", "1e-2", "--learner-updates-per-env-step", "0.0075"],
              "cleaning-car": ["--elden-grad-reg", "1e-3", "--learner-updates-per-env-step", "0.0075"],
              "manipulation": ["--elden-grad-reg", "1e-4", "--learner-updates-per-env-step", "0.03"],
              "*": ["--evaluator-local-samples", "250", "--evaluator-local-capacity", "2000",
                    "--evaluator-min-interval-s", "120"]},
}
"""Per method and env (``*``: every env). ELDEN: lambda is Table 5.2's best per env (Table 5.1's ELDEN
rows); 3,000 updates instead of 10,000 (one update trains 5 members on 32 transitions each, so 3,000
updates process 480k transitions, CDL's 10,000 of 64 process 640k; an ELDEN update costs ~0.12 s of a
core here, a CDL update ~0.03 s); its Jacobians cost ~30 ms a transition, so the live evaluator
scores 250 transitions at most every 2 minutes and keeps 2,000 (the final held-out score uses all)."""
CHAPTER = {"thawing": {"ELDEN": (0.71, 0.57), "pCMI": (0.55, 0.60), "Attn": (0.65, 0.63),
                       "Input Mask": (0.50, 0.40), "Attn Mask": (0.45, 0.47)},
           "cleaning-car": {"ELDEN": (0.78, 0.66), "pCMI": (0.73, 0.78), "Attn": (0.66, 0.55),
                            "Input Mask": (0.50, 0.32), "Attn Mask": (0.47, 0.43)},
           "manipulation": {"ELDEN": (0.66, 0.25), "pCMI": (0.60, 0.28), "Attn": (0.51, 0.22),
                            "Input Mask": (0.50, 0.08), "Attn Mask": (0.52, 0.13)}}
"""Table 5.1 (ROC AUC, F1): Thawing, CarWash, Kitchen."""
ROW_NAMES = {"jacobian": "ELDEN", "pcmi": "pCMI", "attention": "Attn", "input-mask": "Input Mask",
             "attention-mask": "Attn Mask"}
"""Our estimator names -> Table 5.1's rows."""
ESTIMATORS = {"elden": "causal.methods.elden:LOCAL_ESTIMATORS"}
"""Methods whose models support more local-graph estimators than the one the evaluator runs."""
EVAL_SEED = 100_000
"""Evaluation episodes use seeds from here on: never seen in training (runs seed workers from 0-2)."""


def scripted(env, seed: int) -> Any:
    """The env's scripted policy (chapter 5 evaluates on scripted-policy episodes)."""
    base = env.unwrapped
    if type(base).__name__ == "Minecraft2DEnv":
        from envs.minecraft2d import Minecraft2DPolicy
        return Minecraft2DPolicy(base)
    if type(base).__name__ == "ManipulationEnv":
        from envs.skills import SkillPolicy
        return SkillPolicy(env.action_space, seed)
    from envs.household.scripted import scripted_policy
    return scripted_policy(env)


def scripted_transitions(name: str, kwargs: dict[str, Any], episodes: int) -> tuple[np.ndarray, ...]:
    """(state, action, next_state, true local graph) of ``episodes`` scripted episodes, unseen seeds."""
    env = env_entry(name).make(**kwargs)
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    for k in range(episodes):
        obs, _ = env.reset(seed=EVAL_SEED + k)
        policy, done = scripted(env, EVAL_SEED + k), False
        while not done:
            act = policy.act(obs)
            step_action = int(act[0]) if env.unwrapped.env_spec().action_kind == "categorical" else act
            nxt, _, terminated, truncated, info = env.step(step_action)
            rows.append((obs, np.atleast_1d(act).astype(np.float32), nxt, info["local_graph"]))
            obs, done = nxt, terminated or truncated
    env.close()
    return tuple(np.stack([r[i] for r in rows]).astype(np.float32 if i < 3 else np.uint8) for i in range(4))


def estimators(method: str) -> dict[str, Any]:
    """Every local-graph estimator of ``method``'s model: its own, and those :data:`ESTIMATORS` lists."""
    own = get_method(method).local_graph
    found = {own.name: own}
    if method in ESTIMATORS:
        module, _, name = ESTIMATORS[method].partition(":")
        found.update(getattr(importlib.import_module(module), name))
    return found


def score_estimators(method: str, model: Any, transitions: tuple[np.ndarray, ...]) -> dict[str, dict[str, float]]:
    """Every estimator of ``method`` on ``model``, scored on ``transitions`` (:func:`scripted_transitions`):
    pooled over entries (the table's figures), and per entry under ``per_entry``
    (:func:`~causal.graph_metrics.score_local_graphs_per_entry`)."""
    return score_with(estimators(method), model, transitions)


def score_with(found: dict[str, Any], model: Any, transitions: tuple[np.ndarray, ...]) -> dict[str, dict[str, float]]:
    """These estimators (name -> estimator) on ``model``, scored as :func:`score_estimators` does."""
    state, action, next_state, truth = transitions
    tensors = tuple(torch.from_numpy(x) for x in (state, action, next_state))
    scored = {}
    for name, estimator in found.items():
        with torch.no_grad():
            scores = estimator.scores(model, *tensors)
        scored[name] = score_local_graphs(np.asarray(scores), truth, float(estimator.threshold(model)))
        scored[name]["per_entry"] = score_local_graphs_per_entry(np.asarray(scores), truth)
    return scored


def evaluate(run_dir: Path, episodes: int) -> dict[str, Any]:
    cfg = load_run_config(run_dir)
    model = load_model(run_dir)
    transitions = scripted_transitions(cfg.env, env_kwargs(cfg), episodes)
    scored = score_estimators(cfg.method, model, transitions)
    state = transitions[0]
    summary = json.loads((run_dir / "summary.json").read_text())
    return {"env": cfg.env, "seed": cfg.seed, "method": cfg.method, "transitions": int(len(state)),
            "updates": summary.get("updates"), "env_steps": summary.get("env_steps"),
            "scripted": scored[get_method(cfg.method).local_graph.name], "estimators": scored,
            "heldout": {k: summary.get("local_graph", {}).get(k) for k in ("roc_auc", "pr_auc", "best_f1")}}


def train(env: str, seed: int, method: str, run_dir: Path, extra: list[str]) -> None:
    flags = METHOD_FLAGS.get(method, {})
    local_only = get_method(method).global_graph is None
    cmd = [sys.executable, "-m", "services.cli", "run", "--env", env, "--method", method, "--seed", str(seed),
           "--run-dir", str(run_dir), "--router-port", "0", "--dashboard-port", "0", "--metrics-base-port", "0",
           "--max-seconds", "0", "--progress", "false", *BUDGETS[env], *flags.get("*", []), *flags.get(env, []),
           *(["--catch-up-timeout-s", "14400"] if local_only else []), *extra]
    print("$", " ".join(cmd), flush=True)
    with subprocess.Popen(cmd, stdout=subprocess.DEVNULL) as run:
        if local_only:
            _stop_when_trained(run, run_dir, _target_updates(cmd))
        if run.wait() != 0:
            raise subprocess.CalledProcessError(run.returncode, cmd)


def _target_updates(cmd: list[str]) -> float:
    value = {k: v for k, v in zip(cmd, cmd[1:])}
    return CATCH_UP_TOLERANCE * float(value["--learner-updates-per-env-step"]) * float(value["--max-env-steps"])


def _stop_when_trained(run: subprocess.Popen, run_dir: Path, updates: float) -> None:
    """Stop a run of a method without a global graph once its learner has made its share of updates.

    The supervisor's catch-up after the env-step budget waits for a *global* graph report from
    weights trained that long; a local-only method (ELDEN) publishes none, so it would wait for the
    catch-up timeout. This watches the learner's own beats (``causeway status``) instead."""
    while run.poll() is None:
        time.sleep(30)
        status = subprocess.run([sys.executable, "-m", "services.cli", "status", "--run-dir", str(run_dir), "--json"],
                                capture_output=True, text=True)
        try:
            rows = json.loads(status.stdout)["services"]
        except (ValueError, KeyError):
            continue
        done = [r["values"].get("updates", 0) for r in rows if r["service"] == "dynamics-learner"]
        if done and max(done) >= updates:
            subprocess.run([sys.executable, "-m", "services.cli", "stop", "--run-dir", str(run_dir)],
                           capture_output=True)
            return


def scored_estimators(result: dict[str, Any]) -> dict[str, dict[str, float]]:
    """A result's metrics per estimator (results written before several were evaluated hold only
    their method's own, under ``scripted``)."""
    if "estimators" in result:
        return result["estimators"]
    return {get_method(result.get("method", "cdl")).local_graph.name: result["scripted"]}


def rows(results: list[dict[str, Any]]) -> list[tuple[str, str, list[dict[str, float]]]]:
    """(env, Table 5.1 row name, per-seed metrics) for every env and estimator in ``results``."""
    out = []
    for env in dict.fromkeys(r["env"] for r in results):
        scored = [scored_estimators(r) for r in results if r["env"] == env]
        for name in dict.fromkeys(n for s in scored for n in s):
            out.append((env, ROW_NAMES.get(name, name), [s[name] for s in scored if name in s]))
    return out


def table(results: list[dict[str, Any]], method: str) -> str:
    """Each estimator's scores on the scripted episodes beside the chapter's row of the same name
    (results of several methods may be mixed: ``--compare``)."""
    lines = ["| env | estimator | seeds | ROC AUC | PR AUC | best F1 | per entry: ROC AUC / PR AUC / best F1 | "
             "chapter ROC AUC / F1 |", "|---|---|---|---|---|---|---|---|"]
    for env, row, metrics in rows(results):
        stat: Callable[[str], str] = lambda key: _mean_sd([m[key] for m in metrics])  # noqa: E731
        entry: Callable[[str], str] = lambda key: _mean_sd([m["per_entry"][key] for m in metrics  # noqa: E731
                                                            if "per_entry" in m])
        chapter = CHAPTER.get(env, {}).get(row)
        cell = "{:.2f} / {:.2f}".format(*chapter) if chapter else "-"
        lines.append(f"| {env} | {row} | {len(metrics)} | {stat('roc_auc')} | {stat('pr_auc')} | "
                     f"{stat('best_f1')} | {entry('roc_auc')} / {entry('pr_auc')} / {entry('best_f1')} | {cell} |")
    held = [f"{r['env']} s{r['seed']} {r.get('method', 'cdl')}: {_mean_sd([r['heldout']['roc_auc']])} / "
            f"{_mean_sd([r['heldout']['best_f1']])}" for r in results]
    return (f"method {method}; scripted-policy episodes, pooled off-diagonal entries (per entry: the mean over "
            "entries whose labels vary), mean ± sd over seeds\n\n"
            + "\n".join(lines) + "\n\nheld-out (random policy, run's final model) ROC AUC / best F1: "
            + "; ".join(held))


def _mean_sd(values: list[float | None]) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    sd = float(np.std(values, ddof=1)) if len(values) > 1 else 0.0
    return f"{np.mean(values):.3f} ± {sd:.3f}"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["thawing", "cleaning-car", "manipulation"], choices=sorted(BUDGETS))
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--method", default="cdl")
    p.add_argument("--out", type=Path, default=Path("runs/local-table"))
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--reuse", action="store_true", help="evaluate existing run directories instead of training again")
    p.add_argument("--compare", nargs="*", type=Path, default=[],
                   help="other methods' <method>-table.json to print beside (e.g. runs/local-table/cdl-table.json)")
    args, extra = p.parse_known_args(argv)
    if get_method(args.method).local_graph is None:
        p.error(f"method {args.method!r} estimates no local graphs")
    results = []
    for env in args.envs:
        for seed in args.seeds:
            run_dir = args.out / f"{args.method}-{env}-s{seed}"
            if not (args.reuse and (run_dir / "summary.json").exists()):
                train(env, seed, args.method, run_dir, extra)
            results.append(evaluate(run_dir, args.episodes))
            print(json.dumps(results[-1]), flush=True)
    (args.out / f"{args.method}-table.json").write_text(json.dumps(results, indent=1))
    missing = [str(path) for path in args.compare if not path.exists()]
    if missing:
        print(f"not found (left out): {', '.join(missing)}")
    others = [r for path in args.compare if path.exists() for r in json.loads(path.read_text())
              if r["env"] in args.envs]
    print(table(results + others, args.method))


if __name__ == "__main__":
    main()
