"""k-step prediction of future states on Chemical, in and out of distribution (ch. 3.3.3, Figs 3.6-3.8).

Given s_t and a_{t:t+k-1}, a model rolls itself out k steps (feeding back its own predictions) and
is scored on the colours of s_{t+k}: mean accuracy over objects and start states. Colours are the
factors the OOD shift leaves unchanged: OOD states draw object positions from N(0, sigma^2) with
sigma far outside training (the env's ``ood_noise_scale``), and a model that reads positions to
predict colours (a spurious dependency) loses accuracy there while a causal one does not.

Any model enters as a ``step_fn`` (see :mod:`causal.planning`): CDL through
``cdl_rollout_step(model, parents)``, i.e. the causal (parents) mask; the dense baselines through
``causal.baselines.dense_rollout_step``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

from causal.planning import StepFn
from envs.chemical import ChemicalEnv


@dataclass(frozen=True)
class PredictionData:
    """Start states with the next ``k`` real steps: states ``[B, k + 1, D]``, actions ``[B, k, 1]``."""

    states: np.ndarray
    actions: np.ndarray

    @property
    def max_steps(self) -> int:
        return self.actions.shape[1]


def chemical_prediction_data(env: ChemicalEnv, num_starts: int, max_steps: int = 5, seed: int = 0) -> PredictionData:
    """Windows of ``max_steps`` steps from uniformly random-action episodes of ``env``, start times
    drawn uniformly (the data-collection policy of ch. 3.3.2)."""
    rng = np.random.default_rng(seed)
    states, actions = [], []
    episode = 0
    while len(states) < num_starts:
        obs, act = random_episode(env, rng, seed + episode)
        episode += 1
        for t in rng.permutation(len(act) - max_steps + 1)[: num_starts - len(states)]:
            states.append(obs[t : t + max_steps + 1])
            actions.append(act[t : t + max_steps])
    return PredictionData(np.stack(states), np.stack(actions)[..., None].astype(np.float32))


def random_episode(env: ChemicalEnv, rng: np.random.Generator, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One episode of uniformly random actions: observations [T+1, D] and actions [T]."""
    obs, _ = env.reset(seed=seed)
    observations, actions, done = [obs], [], False
    while not done:
        action = int(rng.integers(env.action_space.n))
        obs, _, terminated, truncated, _ = env.step(action)
        observations.append(obs)
        actions.append(action)
        done = terminated or truncated
    return np.stack(observations), np.array(actions)


@torch.no_grad()
def k_step_accuracy(step_fn: StepFn, data: PredictionData, columns: Sequence[int], chunk: int = 512) -> np.ndarray:
    """Mean accuracy ``[k]`` of the predicted categorical ``columns`` after 1..k model steps.

    Start states are rolled out ``chunk`` at a time (CDL's feature tensor grows with the batch)."""
    cols = torch.as_tensor(list(columns), dtype=torch.long)
    hits = np.zeros(data.max_steps)
    for start in range(0, len(data.states), chunk):
        states = torch.from_numpy(data.states[start : start + chunk].astype(np.float32))
        actions = torch.from_numpy(data.actions[start : start + chunk])
        predicted = states[:, 0]
        for k in range(data.max_steps):
            predicted = step_fn(predicted, actions[:, k])
            hits[k] += (predicted[:, cols].round() == states[:, k + 1, cols]).sum().item()
    return hits / (len(data.states) * len(cols))


def chemical_color_columns(env: ChemicalEnv) -> list[int]:
    """Flat columns of the colour factors (``obj{k}.color``)."""
    return [3 * k for k in range(env.num_objects)]


def evaluate_chemical_prediction(step_fn: StepFn, env_kwargs: dict[str, Any], noise_scales: Sequence[float] = (),
                                 num_starts: int = 5000, max_steps: int = 5, seed: int = 0,
                                 env_cls: type[ChemicalEnv] = ChemicalEnv) -> dict[str, np.ndarray]:
    """k-step colour accuracy on ID states (``"id"``) and OOD states for each noise scale sigma
    (``"ood_<sigma>"``), each from ``num_starts`` windows (the chapter uses 5K transitions).

    ``env_kwargs`` builds the training environment (same graph, tables and sizes for all); OOD
    environments add ``ood_noise_scale=sigma``. ``env_cls`` may be a Chemical subclass whose
    observation appends factors (``ChemicalMatchEnv``'s goals) when the model was trained on it.
    """
    settings: dict[str, dict[str, Any]] = {"id": dict(env_kwargs, ood_noise_scale=None)}
    settings.update({f"ood_{sigma:g}": dict(env_kwargs, ood_noise_scale=sigma) for sigma in noise_scales})
    results = {}
    for name, kwargs in settings.items():
        env = env_cls(**kwargs)
        data = chemical_prediction_data(env, num_starts, max_steps, seed)
        results[name] = k_step_accuracy(step_fn, data, chemical_color_columns(env))
    return results
