"""CDL acting on what it learned (ch. 3.2.4): causal rollouts + reward predictor + CEM on Match.

Slow (about a minute): trains a small CDL model on random Chemical data, a reward predictor on the
abstraction plus the goal factors, then plans with CEM; it must beat random actions by far, and
score exactly the same on OOD states, since neither the abstraction nor the causal colour model
reads a position.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np
import pytest
import torch

from causal.abstraction import cdl_abstraction
from causal.cdl import CDLConfig
from causal.cdl_trainer import CDLTrainer
from causal.factored import FactorLayout
from causal.planning import CEMPlanner, cdl_rollout_step
from causal.prediction_eval import chemical_prediction_data
from causal.reward_model import RewardModel
from causal.rl.base import ActionSpec
from envs.chemical import ChemicalEnv
from envs.chemical_match import ChemicalMatchEnv

pytestmark = pytest.mark.slow
ENV = {"graph": "chain", "num_objects": 3}


def train_cdl(env: ChemicalEnv, rng: np.random.Generator) -> CDLTrainer:
    trainer = CDLTrainer(FactorLayout.from_spec(env.env_spec()),
                         CDLConfig(feature_hidden=32, feature_dim=32, predictor_hidden=32, lr=3e-3), seed=0)
    trainer.set_parents(env.global_graph.astype(bool))
    data = chemical_prediction_data(env, 5000, 1, seed=0)
    s, a, n = (torch.from_numpy(x) for x in (data.states[:, 0], data.actions[:, 0], data.states[:, 1]))
    for _ in range(1000):
        index = torch.from_numpy(rng.integers(0, len(s), 64))
        trainer.update(s[index], a[index], n[index])
    return trainer


def train_reward(env: ChemicalMatchEnv, kept: tuple[int, ...], rng: np.random.Generator) -> RewardModel:
    states, actions, rewards = [], [], []
    for episode in range(100):
        obs, _ = env.reset(seed=episode)
        for _ in range(env.episode_length):
            action = int(rng.integers(env.action_space.n))
            states.append(obs)
            actions.append(action)
            obs, reward, *_ = env.step(action)
            rewards.append(reward)
    s, r = torch.from_numpy(np.array(states)), torch.tensor(rewards)
    a = torch.tensor(actions, dtype=torch.float32)[:, None]
    goals = range(3 * env.num_objects, 4 * env.num_objects)
    model = RewardModel(FactorLayout.from_spec(env.env_spec()), [*kept, *goals], seed=0)
    for _ in range(3000):
        index = torch.from_numpy(rng.integers(0, len(s), 64))
        model.fit_step(s[index], a[index], r[index])
    return model


def episode_returns(env: ChemicalMatchEnv, act: Callable[[np.ndarray], int], episodes: int = 10) -> np.ndarray:
    returns = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=1000 + episode)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(act(obs))
            total, done = total + reward, terminated or truncated
        returns.append(total)
    return np.array(returns)


def test_cem_on_cdl_and_the_reward_predictor_solves_match_in_and_out_of_distribution() -> None:
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    env = ChemicalEnv(**ENV)
    trainer, abstraction = train_cdl(env, rng), cdl_abstraction(env.global_graph)
    match = ChemicalMatchEnv(**ENV)
    reward = train_reward(match, abstraction.kept, rng)
    step = cdl_rollout_step(trainer.model, torch.from_numpy(env.global_graph.astype(bool)), abstraction.kept)
    action = ActionSpec.from_space(match.action_space)

    def planned(env_kwargs: dict[str, Any]) -> np.ndarray:
        planner = CEMPlanner(step, reward, action, seed=0)
        return episode_returns(ChemicalMatchEnv(**env_kwargs), lambda o: int(planner.plan(torch.from_numpy(o))))

    in_distribution = planned(ENV)
    random = episode_returns(match, lambda o: int(rng.integers(match.action_space.n)))
    assert in_distribution.mean() > random.mean() + 15, (in_distribution.mean(), random.mean())
    np.testing.assert_array_equal(planned({**ENV, "ood_noise_scale": 100.0}), in_distribution)
