"""In-process experience collection: the single-process form of an env-worker feeding a learner.

:class:`RolloutCollector` steps ``N`` environments for PPO, batching the policy's forward pass;
:class:`StepCollector` steps one environment into a replay buffer for SAC. Environment ``i`` is
seeded with ``seed + i``. Episodes reset by hand (no vector-env autoreset), so the final
observation of a truncated episode is at hand for its bootstrap value.
"""
from __future__ import annotations

from typing import Sequence

import gymnasium as gym
import numpy as np
import torch

from causal.rl.base import Agent, RolloutBatch
from causal.rl.ppo import PPOAgent
from causal.rl.replay import UniformReplay


class RolloutCollector:
    """Collects :class:`RolloutBatch` es from ``envs`` with a :class:`PPOAgent`."""

    def __init__(self, envs: Sequence[gym.Env], seed: int = 0) -> None:
        self.envs = list(envs)
        self.obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(self.envs)]).astype(np.float32)
        self.returns = np.zeros(len(self.envs))
        self.episode_returns: list[float] = []

    def collect(self, agent: PPOAgent, steps: int) -> RolloutBatch:
        """``steps`` steps of every environment; a truncated episode's reward gets ``gamma V(s_T)``."""
        obs, actions, log_probs, values, rewards, dones = [], [], [], [], [], []
        for _ in range(steps):
            step = agent.policy_step(self.obs)
            obs.append(torch.from_numpy(self.obs.copy()))
            actions.append(step.actions)
            log_probs.append(step.log_probs)
            values.append(step.values)
            reward, done = self._step_all(step.env_actions, agent)
            rewards.append(torch.from_numpy(reward))
            dones.append(torch.from_numpy(done))
        return RolloutBatch(torch.stack(obs), torch.stack(actions), torch.stack(log_probs), torch.stack(values),
                            torch.stack(rewards), torch.stack(dones), torch.from_numpy(self.obs.copy()),
                            policy_version=agent.version)

    def _step_all(self, env_actions: np.ndarray, agent: PPOAgent) -> tuple[np.ndarray, np.ndarray]:
        rewards = np.zeros(len(self.envs), np.float32)
        dones = np.zeros(len(self.envs), bool)
        for i, env in enumerate(self.envs):
            next_obs, reward, terminated, truncated, _ = env.step(env_actions[i])
            self.returns[i] += reward
            if truncated and not terminated:
                reward += agent.cfg.gamma * float(agent.value(next_obs)[0])
            rewards[i], dones[i] = reward, terminated or truncated
            if dones[i]:
                self.episode_returns.append(float(self.returns[i]))
                self.returns[i] = 0.0
                next_obs, _ = env.reset()
            self.obs[i] = next_obs
        return rewards, dones


class StepCollector:
    """Steps one environment with an agent (or uniformly random actions) into a replay buffer."""

    def __init__(self, env: gym.Env, replay: UniformReplay, seed: int = 0) -> None:
        self.env, self.replay = env, replay
        self.obs, _ = env.reset(seed=seed)
        env.action_space.seed(seed)
        self.episode_return = 0.0
        self.episode_returns: list[float] = []

    def step(self, agent: Agent | None = None) -> None:
        """One environment step; ``agent=None`` samples the action space (warm-up)."""
        action = self.env.action_space.sample() if agent is None else agent.act(self.obs)
        next_obs, reward, terminated, truncated, _ = self.env.step(action)
        self.replay.add(self.obs[None], np.reshape(action, (1, -1)), np.array([reward]), next_obs[None],
                        np.array([terminated]))
        self.episode_return += float(reward)
        self.obs = next_obs
        if terminated or truncated:
            self.episode_returns.append(self.episode_return)
            self.episode_return = 0.0
            self.obs, _ = self.env.reset()


def evaluate(env: gym.Env, agent: Agent, episodes: int, seed: int = 0) -> list[float]:
    """Undiscounted returns of ``episodes`` deterministic episodes, episode ``k`` seeded ``seed + k``."""
    returns = []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(agent.act(obs, deterministic=True))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return returns
