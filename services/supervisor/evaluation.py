"""After a run on an environment whose registry entry names the ``chemical`` evaluation suite, with a
method whose model can be rolled out (``Method.rollout_step``): evaluate the run's own models the
way chapter 3 does, for the summary.

- **Prediction** (Figs 3.6-3.8): the dynamics-learner's final model, in causal mode on the last
  graph report's graph, rolled out 1..5 steps on ID states and on OOD states (positions with noise
  scale sigma). Colour accuracy per step.
- **Match** (ch. 3.3.5, Figure 3.11), for ``--task match`` runs: CEM planning with that frozen model
  in its abstract space plus a reward predictor learned on random Match episodes (eq. 3.5), and the
  policy-learner's final policy acting deterministically; episode reward on ID and OOD states, with
  random actions on the same start states for reference.

The dense baselines are not trained by a run;
``benchmarks/bench_ch3_generalisation.py`` compares CDL with them on identical data.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from torch import nn

from causal.abstraction import Abstraction
from causal.generalisation import (MatchConfig, acted_returns, match_dataset, per_setting, planner_returns,
                                   random_returns, reward_inputs)
from causal.method import Method
from causal.methods import get_method, model_from_config_json
from causal.prediction_eval import evaluate_chemical_prediction
from envs.chemical import ChemicalEnv
from envs.chemical_match import ChemicalMatchEnv
from envs.registry import EnvEntry
from proto.messages import GraphReport
from services.runtime.checkpoint import load_checkpoint

log = logging.getLogger("supervisor")
SUITE = "chemical"
"""The ``EnvEntry.evaluation`` this module evaluates."""


def applies(entry: EnvEntry, method: Method) -> bool:
    """Whether this evaluation suite applies to a run of ``method`` on ``entry``."""
    return entry.evaluation == SUITE and method.rollout_step is not None


@dataclass(frozen=True)
class EvaluationConfig:
    """Sizes of the post-run evaluation (small enough to take well under a minute on 10 objects)."""

    noise_scales: tuple[float, ...] = (0.1, 1.0, 10.0)
    prediction_starts: int = 1000
    max_steps: int = 5
    match_noise_scales: tuple[float, ...] = (1.0,)
    match: MatchConfig = field(default_factory=lambda: MatchConfig(reward_episodes=200, episodes=16))
    seed: int = 12345


def evaluate_run(run_dir: Path, entry: EnvEntry, env_kwargs: dict[str, Any], report: GraphReport,
                 policy: Callable[[np.ndarray], Any] | None = None, cfg: EvaluationConfig = EvaluationConfig(),
                 ) -> dict[str, Any]:
    """``{"prediction": {...}, "match": {...}}`` for a Chemical run, from its checkpoints.

    ``policy`` (observation -> action), when given on a Match run, is evaluated beside CEM."""
    env_cls = entry.env_class()
    model = load_model(run_dir)
    method = get_method(report.kind)
    graph = torch.from_numpy(report.adjacency.astype(bool))
    started = time.perf_counter()
    accuracy = evaluate_chemical_prediction(method.rollout_step(model, graph), env_kwargs, cfg.noise_scales,
                                            cfg.prediction_starts, cfg.max_steps, cfg.seed, env_cls)
    out: dict[str, Any] = {
        "prediction": {"model": f"{method.name} (run's final weights, causal mode on the last graph)",
                       "starts": cfg.prediction_starts,
                       "colour_accuracy": {k: [round(float(x), 4) for x in v] for k, v in accuracy.items()}}}
    if issubclass(env_cls, ChemicalMatchEnv):
        out["match"] = match_evaluation(model, method, report, env_kwargs, policy, cfg)
    out["evaluation_seconds"] = round(time.perf_counter() - started, 1)
    return out


def load_model(run_dir: Path) -> nn.Module:
    """The dynamics-learner's last checkpointed model, rebuilt (through the method registry) from the
    model config that the checkpoint's fingerprint carries, so any run's checkpoint loads without its
    service config."""
    path = run_dir / "checkpoints" / "dynamics-learner-0.pt"
    saved = load_checkpoint(path)
    if saved is None:
        raise FileNotFoundError(f"no dynamics-learner checkpoint at {path}")
    return model_from_checkpoint(saved)


def checkpoint_model_config(saved: dict) -> str:
    """The model configuration (``Method.config_json``) of a loaded dynamics-learner checkpoint, with
    every setting the run last trained under (``model_config``). The fingerprint leaves the resumable
    ones out (the learning-rate schedule), so a checkpoint written before ``model_config`` was kept
    gives those at their defaults."""
    return saved.get("model_config") or json.dumps(json.loads(saved["fingerprint"])["model"], sort_keys=True)


def model_from_checkpoint(saved: dict) -> nn.Module:
    """The model of a loaded dynamics-learner checkpoint (:func:`checkpoint_model_config`), in eval mode."""
    model = model_from_config_json(checkpoint_model_config(saved))
    model.load_state_dict(saved["trainer"]["model"])
    return model.eval()


def match_evaluation(model: nn.Module, method: Method, report: GraphReport, env_kwargs: dict[str, Any],
                     policy: Callable[[np.ndarray], Any] | None, cfg: EvaluationConfig) -> dict[str, Any]:
    """Episode rewards of CEM with the run's model, of the run's policy and of random actions."""
    num_objects = ChemicalEnv(**env_kwargs).num_objects
    state_factors = 3 * num_objects
    # The Match observation appends the goal factors, which the run's graph covers too (each depends
    # on itself only). Planning rolls out Chemical's kept factors; the goals enter the reward
    # predictor as provided factors (reward_inputs), as in the chapter.
    abstraction = Abstraction(tuple(j for j in report.controllable if j < state_factors),
                              tuple(j for j in report.action_relevant if j < state_factors), ())
    kept = abstraction.kept
    data = match_dataset(env_kwargs, cfg.match.reward_episodes, cfg.seed)
    step = method.rollout_step(model, torch.from_numpy(report.adjacency.astype(bool)), kept)
    out: dict[str, Any] = {
        "episodes": cfg.match.episodes,
        "abstraction_kept": [report.factor_names[j] for j in kept],
        "returns": {f"CEM + {method.name.upper()}": planner_returns(step, reward_inputs(abstraction, num_objects), env_kwargs,
                                                  cfg.match_noise_scales, data, cfg.match, cfg.seed)}}
    if policy is not None:
        deterministic = lambda obs: int(np.asarray(policy(obs)).reshape(-1)[0])  # noqa: E731
        out["returns"]["policy"] = per_setting(lambda kwargs: acted_returns(deterministic, kwargs, cfg.match.episodes),
                                               env_kwargs, cfg.match_noise_scales)
    out["returns"]["random"] = per_setting(lambda kwargs: random_returns(kwargs, cfg.match.episodes, cfg.seed),
                                           env_kwargs, cfg.match_noise_scales)
    out["mean"] = {who: {name: round(float(np.mean(r)), 3) for name, r in per.items()}
                   for who, per in out["returns"].items()}
    return out


def plot_evaluation(evaluation: dict[str, Any], path: Path) -> None:
    """Prediction accuracy per step (ID and each OOD scale) and, for Match, mean episode rewards."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    match = evaluation.get("match")
    fig, axes = plt.subplots(1, 2 if match else 1, figsize=(11 if match else 5.5, 3.8), squeeze=False)
    ax = axes[0][0]
    for setting, acc in evaluation["prediction"]["colour_accuracy"].items():
        label = "ID" if setting == "id" else f"OOD sigma={setting[4:]}"
        ax.plot(range(1, len(acc) + 1), acc, marker="o", label=label, linestyle="-" if setting == "id" else "--")
    ax.set_xticks(range(1, len(acc) + 1))
    ax.set_xlabel("prediction steps")
    ax.set_ylabel("colour accuracy")
    ax.set_ylim(0, 1.02)
    ax.set_title("k-step prediction (this run's model)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    if match:
        ax = axes[0][1]
        who = list(match["mean"])
        settings = list(match["mean"][who[0]])
        width = 0.8 / len(settings)
        for k, setting in enumerate(settings):
            ax.bar(np.arange(len(who)) + k * width, [match["mean"][w][setting] for w in who], width,
                   label="ID" if setting == "id" else f"OOD sigma={setting[4:]}")
        ax.set_xticks(np.arange(len(who)) + width * (len(settings) - 1) / 2, who)
        ax.set_ylabel(f"mean episode reward ({match['episodes']} episodes)")
        ax.set_title("Match")
        ax.legend()
        ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
