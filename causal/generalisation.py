"""Chapter 3's generalisation experiments on our implementation: CDL against the dense baselines.

Everything here runs in one process, without the bus, on the same data for every model:

1. :func:`random_transitions`: the chapter's Chemical data-collection policy (uniformly random
   actions), split by episode into training and held-out transitions.
2. :func:`train_dynamics`: CDL (eq. 3.3, its graph re-derived from CMI on held-out data every
   ``graph_every`` updates, as the graph-evaluator does for the services), the Monolithic MLP and
   the Modular model with matched parameter counts, all fed the *same* minibatches for the same
   number of updates (ch. 3.3.3: "after training all methods on the same set of collected data").
3. :func:`prediction_table`: 1..k-step colour accuracy on ID states and on OOD states whose object
   positions are drawn with an unseen noise scale sigma (Figs 3.6-3.8).
4. :func:`match_returns`: the Match task (ch. 3.3.5). The dynamics are frozen; a reward predictor is
   learned per model (CDL: on its abstraction plus the goal factors, eq. 3.5; dense models: on every
   factor); a CEM planner acts with each model's rollouts. Episode reward on ID and OOD states
   (Figure 3.11).

The benchmark ``benchmarks/bench_ch3_generalisation.py`` drives it; the supervisor uses
:func:`prediction_table` and :func:`match_returns` on the run's own CDL model for the run summary.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from causal.abstraction import Abstraction, cdl_abstraction
from causal.baselines import (DenseDynamicsTrainer, ModularModel, MonolithicModel, dense_rollout_step,
                              matched_monolithic, parameter_count)
from causal.cdl import CDLConfig
from causal.abstraction import with_self_edges
from causal.cdl_trainer import CDLTrainer
from causal.factored import FactorLayout
from causal.graph_metrics import score_graph
from causal.planning import CEMConfig, CEMPlanner, StepFn, cdl_rollout_step
from causal.prediction_eval import evaluate_chemical_prediction, random_episode
from causal.reward_model import RewardModel
from causal.rl.base import ActionSpec
from envs.chemical import ChemicalEnv
from envs.chemical_match import ChemicalMatchEnv

MODELS = ("CDL", "Monolithic", "Modular")
Progress = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


@dataclass(frozen=True)
class Transitions:
    """Flat transitions: ``state``/``next_state`` ``[N, D]`` float32, ``action`` ``[N, 1]`` float32."""

    state: np.ndarray
    action: np.ndarray
    next_state: np.ndarray

    def __len__(self) -> int:
        return len(self.state)

    def tensors(self, index: np.ndarray | slice = slice(None)) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return tuple(torch.from_numpy(x[index]) for x in (self.state, self.action, self.next_state))


def random_transitions(env_kwargs: Mapping[str, Any], count: int, seed: int = 0,
                       heldout_fraction: float = 0.1) -> tuple[Transitions, Transitions]:
    """``count`` transitions of uniformly random actions on ``ChemicalEnv(**env_kwargs)``; whole
    episodes go to the held-out set with probability ``heldout_fraction``. Returns (train, heldout); the
    held-out set is empty when ``heldout_fraction`` is 0."""
    env = ChemicalEnv(**env_kwargs)
    rng = np.random.default_rng(seed)
    parts: dict[bool, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {False: [], True: []}
    total, episode = 0, 0
    while total < count:
        observations, actions = random_episode(env, rng, seed * 1_000_003 + episode)
        s = observations.astype(np.float32)
        parts[bool(rng.random() < heldout_fraction)].append((s[:-1], actions.astype(np.float32)[:, None], s[1:]))
        total += len(actions)
        episode += 1

    def join(chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray]], wanted: bool = True) -> Transitions:
        if not chunks and not wanted:
            d = env.env_spec().num_factors
            return Transitions(np.zeros((0, d), np.float32), np.zeros((0, 1), np.float32), np.zeros((0, d), np.float32))
        if not chunks:
            raise ValueError("no episode landed in this split: collect more transitions")
        return Transitions(*(np.concatenate(column) for column in zip(*chunks)))

    return join(parts[False]), join(parts[True], wanted=heldout_fraction > 0)


@dataclass(frozen=True)
class TrainingConfig:
    """How the three dynamics models are trained (CDL's architecture comes from ``cdl``)."""

    updates: int = 4000
    graph_every: int = 250
    """Re-derive CDL's graph (its causal-term parents) from held-out CMI every this many updates."""
    cmi_samples: int = 2000
    cmi_ema: float = 0.5
    """Weight of the previous CMI estimate in the moving average (the graph-evaluator's default)."""
    cdl: CDLConfig = field(default_factory=CDLConfig)


@dataclass
class TrainedDynamics:
    """The three trained models and CDL's learned graph."""

    layout: FactorLayout
    cdl: CDLTrainer
    monolithic: MonolithicModel
    modular: ModularModel
    cmi: np.ndarray
    threshold: float
    seconds: dict[str, float]

    @property
    def graph(self) -> np.ndarray:
        """CDL's learned graph ``[d_S, d_S + 1]`` with self-edges (Assumption 4)."""
        return with_self_edges(self.cmi >= self.threshold)

    def parameters(self) -> dict[str, int]:
        return {"CDL": parameter_count(self.cdl.model), "Monolithic": parameter_count(self.monolithic),
                "Modular": parameter_count(self.modular)}

    def step_fns(self, factors: Sequence[int] | None = None) -> dict[str, StepFn]:
        """Deterministic rollout steps of every model; CDL in causal mode on its learned graph
        (rolling out only ``factors`` when given, i.e. planning in its abstract space). Columns past
        the model's state (a task's goal factors) are carried through unchanged."""
        dim = self.layout.state_dim
        return {"CDL": cdl_rollout_step(self.cdl.model, torch.from_numpy(self.graph), factors),
                "Monolithic": carry_extra_columns(dense_rollout_step(self.monolithic), dim),
                "Modular": carry_extra_columns(dense_rollout_step(self.modular), dim)}


def carry_extra_columns(step_fn: StepFn, state_dim: int) -> StepFn:
    """A step over the first ``state_dim`` columns that copies any further columns unchanged."""

    def step(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        if states.shape[1] == state_dim:
            return step_fn(states, actions)
        return torch.cat([step_fn(states[:, :state_dim], actions), states[:, state_dim:]], dim=1)

    return step


def train_dynamics(layout: FactorLayout, train: Transitions, heldout: Transitions,
                   cfg: TrainingConfig = TrainingConfig(), seed: int = 0,
                   progress: Progress = _quiet) -> TrainedDynamics:
    """CDL, Monolithic and Modular on identical minibatches for ``cfg.updates`` updates each."""
    cdl = CDLTrainer(layout, cfg.cdl, seed=seed)
    torch.manual_seed(seed)
    monolithic = matched_monolithic(cdl.model)
    modular = ModularModel(layout, cfg.cdl)
    dense = {"Monolithic": DenseDynamicsTrainer(monolithic, seed=seed),
             "Modular": DenseDynamicsTrainer(modular, seed=seed)}
    rng = np.random.default_rng(seed)
    held = rng.choice(len(heldout), min(cfg.cmi_samples, len(heldout)), replace=False)
    held_s, held_a, held_n = heldout.tensors(held)
    seconds = dict.fromkeys(MODELS, 0.0)
    cmi: np.ndarray | None = None
    for update in range(1, cfg.updates + 1):
        batch = train.tensors(rng.integers(0, len(train), cfg.cdl.batch_size))
        started = time.perf_counter()
        cdl.update(*batch)
        seconds["CDL"] += time.perf_counter() - started
        for name, trainer in dense.items():
            started = time.perf_counter()
            trainer.update(*batch)
            seconds[name] += time.perf_counter() - started
        if update % cfg.graph_every == 0 or update == cfg.updates:
            estimate = cdl.model.cmi(held_s, held_a, held_n).numpy()
            cmi = estimate if cmi is None else cfg.cmi_ema * cmi + (1 - cfg.cmi_ema) * estimate
            cdl.set_parents(cmi >= cfg.cdl.cmi_threshold)
            progress(f"update {update}/{cfg.updates}: {int((cmi >= cfg.cdl.cmi_threshold).sum())} CMI edges")
    assert cmi is not None
    return TrainedDynamics(layout, cdl, monolithic, modular, cmi, cfg.cdl.cmi_threshold,
                           {k: round(v, 1) for k, v in seconds.items()})


def graph_scores(trained: TrainedDynamics, truth: np.ndarray) -> dict[str, float]:
    """CDL's learned graph against the truth (the scores of the run summary)."""
    return score_graph(trained.cmi, truth, trained.threshold)


def prediction_table(step_fns: Mapping[str, StepFn], env_kwargs: Mapping[str, Any], noise_scales: Sequence[float],
                     num_starts: int = 5000, max_steps: int = 5, seed: int = 0,
                     progress: Progress = _quiet) -> dict[str, dict[str, list[float]]]:
    """``{model: {"id" | "ood_<sigma>": [accuracy after 1..k steps]}}`` (Figs 3.6-3.8)."""
    table = {}
    for name, step in step_fns.items():
        progress(f"prediction: {name}")
        results = evaluate_chemical_prediction(step, dict(env_kwargs), noise_scales, num_starts, max_steps, seed)
        table[name] = {setting: [round(float(x), 4) for x in acc] for setting, acc in results.items()}
    return table


@dataclass(frozen=True)
class MatchConfig:
    """The Match experiment: reward-predictor training and CEM evaluation (reference CEM settings)."""

    reward_episodes: int = 200
    reward_updates: int = 4000
    reward_batch: int = 64
    episodes: int = 32
    parallel: int = 16
    """Episodes planned together (CEM is batched over start states)."""
    cem: CEMConfig = field(default_factory=CEMConfig)


def match_dataset(match_kwargs: Mapping[str, Any], episodes: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(states, actions, rewards) of uniformly random actions on Match: the reward predictor's data."""
    env = ChemicalMatchEnv(**match_kwargs)
    rng = np.random.default_rng(seed)
    states, actions, rewards = [], [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed * 1_000_003 + episode)
        done = False
        while not done:
            action = int(rng.integers(env.action_space.n))
            states.append(obs)
            actions.append(action)
            obs, reward, terminated, truncated, _ = env.step(action)
            rewards.append(reward)
            done = terminated or truncated
    return (torch.from_numpy(np.array(states, dtype=np.float32)), torch.tensor(actions, dtype=torch.float32)[:, None],
            torch.tensor(rewards, dtype=torch.float32))


def train_reward_model(match_kwargs: Mapping[str, Any], inputs: Sequence[int],
                       data: tuple[torch.Tensor, torch.Tensor, torch.Tensor], cfg: MatchConfig,
                       seed: int = 0) -> RewardModel:
    """Eq. 3.5: the reward predictor on ``inputs`` (factor indices of the Match observation)."""
    layout = FactorLayout.from_spec(ChemicalMatchEnv(**match_kwargs).env_spec())
    model = RewardModel(layout, inputs, seed=seed)
    states, actions, rewards = data
    rng = np.random.default_rng(seed)
    for _ in range(cfg.reward_updates):
        index = torch.from_numpy(rng.integers(0, len(states), cfg.reward_batch))
        model.fit_step(states[index], actions[index], rewards[index])
    return model


def reward_inputs(abstraction: Abstraction | None, num_objects: int) -> list[int]:
    """The reward predictor's factors in the Match observation: CDL's abstraction (or, for a dense
    model, every Chemical factor) plus the provided goal factors."""
    state_factors = 3 * num_objects
    kept = range(state_factors) if abstraction is None else abstraction.kept
    return [*kept, *range(state_factors, state_factors + num_objects)]


MATCH_START_SEED = 10_000
"""Episode i of every Match evaluation starts from ``reset(seed=MATCH_START_SEED + i)``, so planners,
policies and random actions are compared on the same start states."""


def acted_returns(act: Callable[[np.ndarray], int], match_kwargs: Mapping[str, Any], episodes: int) -> np.ndarray:
    """Episode rewards of ``act`` (observation -> action index) on the evaluation start states."""
    env = ChemicalMatchEnv(**match_kwargs)
    returns = []
    for i in range(episodes):
        obs, _ = env.reset(seed=MATCH_START_SEED + i)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(int(act(obs)))
            total, done = total + reward, terminated or truncated
        returns.append(total)
    return np.array(returns)


def per_setting(returns: Callable[[dict[str, Any]], np.ndarray], env_kwargs: Mapping[str, Any],
                noise_scales: Sequence[float]) -> dict[str, list[float]]:
    """``{"id" | "ood_<sigma>": rounded episode rewards}`` of ``returns(match_kwargs)`` per setting."""
    return {setting: [round(float(x), 3) for x in returns(kwargs)]
            for setting, kwargs in match_settings(env_kwargs, noise_scales).items()}


def planned_returns(step_fn: StepFn, reward_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                    match_kwargs: Mapping[str, Any], cfg: MatchConfig, seed: int = 0) -> np.ndarray:
    """Episode rewards of CEM acting with (``step_fn``, ``reward_fn``) on ``cfg.episodes`` Match
    episodes (start seeds ``MATCH_START_SEED + i``), ``cfg.parallel`` at a time."""
    returns: list[float] = []
    for first in range(0, cfg.episodes, cfg.parallel):
        envs = [ChemicalMatchEnv(**match_kwargs) for _ in range(min(cfg.parallel, cfg.episodes - first))]
        action_spec = ActionSpec.from_space(envs[0].action_space)
        planner = CEMPlanner(step_fn, reward_fn, action_spec, cfg.cem, seed=seed + first)
        obs = np.stack([env.reset(seed=MATCH_START_SEED + first + i)[0] for i, env in enumerate(envs)])
        totals = np.zeros(len(envs))
        live = np.ones(len(envs), dtype=bool)
        while live.any():
            actions = planner.plan(torch.from_numpy(obs[live].astype(np.float32))).numpy()
            for slot, action in zip(np.flatnonzero(live), actions):
                obs[slot], reward, terminated, truncated, _ = envs[slot].step(int(action))
                totals[slot] += reward
                live[slot] = not (terminated or truncated)
        returns.extend(totals.tolist())
    return np.array(returns)


def match_settings(env_kwargs: Mapping[str, Any], noise_scales: Sequence[float]) -> dict[str, dict[str, Any]]:
    """Environment kwargs of the ID setting (``"id"``) and of each OOD noise scale (``"ood_<sigma>"``)."""
    settings = {"id": dict(env_kwargs, ood_noise_scale=None)}
    settings.update({f"ood_{s:g}": dict(env_kwargs, ood_noise_scale=s) for s in noise_scales})
    return settings


def planner_returns(step_fn: StepFn, inputs: Sequence[int], env_kwargs: Mapping[str, Any],
                    noise_scales: Sequence[float], data: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                    cfg: MatchConfig = MatchConfig(), seed: int = 0) -> dict[str, list[float]]:
    """Learn the reward predictor on ``inputs`` from ``data`` (the dynamics stay frozen), then
    ``{"id" | "ood_<sigma>": episode rewards}`` of CEM planning with ``step_fn``."""
    reward = train_reward_model(env_kwargs, inputs, data, cfg, seed)
    return per_setting(lambda kwargs: planned_returns(step_fn, reward, kwargs, cfg, seed), env_kwargs, noise_scales)


def match_returns(trained: TrainedDynamics, env_kwargs: Mapping[str, Any], noise_scales: Sequence[float],
                  cfg: MatchConfig = MatchConfig(), seed: int = 0, models: Sequence[str] = MODELS,
                  progress: Progress = _quiet) -> dict[str, dict[str, list[float]]]:
    """``{model: {"id" | "ood_<sigma>": episode rewards}}`` of CEM with each model (Figure 3.11),
    plus ``"Random"`` for reference. ``env_kwargs`` are Chemical's (Match adds the goal).

    CDL plans in its abstract space and its reward predictor reads the abstraction plus the goal
    factors (eq. 3.5); the dense models roll out and read every factor."""
    num_objects = ChemicalEnv(**env_kwargs).num_objects
    data = match_dataset(env_kwargs, cfg.reward_episodes, seed)
    abstraction = cdl_abstraction(trained.graph)
    out: dict[str, dict[str, list[float]]] = {}
    for name in models:
        progress(f"match: CEM with {name}")
        kept = abstraction.kept if name == "CDL" else None
        inputs = reward_inputs(abstraction if name == "CDL" else None, num_objects)
        out[name] = planner_returns(trained.step_fns(kept)[name], inputs, env_kwargs, noise_scales, data, cfg, seed)
    out["Random"] = per_setting(lambda kwargs: random_returns(kwargs, cfg.episodes, seed), env_kwargs, noise_scales)
    return out


def random_returns(match_kwargs: Mapping[str, Any], episodes: int, seed: int = 0) -> np.ndarray:
    """Episode rewards of uniformly random actions on the same start states as :func:`planned_returns`."""
    rng = np.random.default_rng(seed)
    actions = ChemicalMatchEnv(**match_kwargs).action_space.n
    return acted_returns(lambda obs: rng.integers(actions), match_kwargs, episodes)
