"""SkiLD's downstream task learning (ch. 6.2.4): a task policy that picks skills, the skills frozen.

The task policy is PPO (:class:`causal.rl.ppo.PPOAgent`) over the one-hot state; its action is a
skill ``z = (G, b)``: one of the pre-trained history's targets times the ``K`` diversity indices
(DIAYN: one of its ``K`` skills). A picked skill runs its frozen low-level policy greedily for ``L``
steps, or until the episode ends; the decision's reward is the sum of the task rewards over those
steps (a semi-MDP: the discount applies once per decision). ``agent=None`` is the baseline "PPO
from scratch" on primitive actions, one decision per step.

:func:`train_task` returns the success curve: per update, the env steps so far and the share of the
episodes finished since the previous update that succeeded.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from causal.rl.base import ActionSpec, RolloutBatch
from causal.rl.ppo import PPOAgent, PPOConfig
from causal.skild import graph_matches, object_graphs
from causal.skild_agent import SkiLDAgent, one_hot_states
from causal.skild_pretrain import HouseholdBatch
from proto.settings import doc


@dataclass(frozen=True)
class TaskConfig:
    """Fine-tuning budget and the task policy's PPO settings."""

    env_steps: int = doc(50_000, "env steps of task learning (primitive steps, all envs together)")
    num_envs: int = doc(8, "envs stepped together")
    decisions: int = doc(16, "decisions per env per PPO update (primitive PPO: steps)")
    lr: float = doc(3e-4, "Adam learning rate of the task policy")
    gamma: float = doc(0.99, "discount per decision")
    entropy_coef: float = doc(0.01, "entropy bonus of the task policy")
    end_on_target: bool = doc(False, "a SkiLD skill also ends on the step it induces its target graph (the "
                                     "chapter runs every skill for L steps)")


class SkillOptions:
    """A frozen skill library as the task policy's actions: option ``o`` -> ``(target o // K, b = o % K)``."""

    def __init__(self, agent: SkiLDAgent) -> None:
        self.agent = agent
        self.k = agent.k
        self.factors, self.rows = agent.history.target_arrays(agent.n + 1)
        self.targets = max(len(self.factors), 1) if agent.mode == "skild" else 1

    @property
    def count(self) -> int:
        return self.targets * self.k

    def skills(self, options: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(factor, row, b)`` of each option."""
        slot, b = options // self.k, options % self.k
        if self.agent.mode == "diayn" or not len(self.factors):
            return np.zeros(len(options), np.int64), np.zeros((len(options), self.agent.n + 1), bool), b
        return self.factors[slot], self.rows[slot], b


def train_task(agent: SkiLDAgent | None, env: str, task: str, cfg: TaskConfig, seed: int = 0,
               episode_length: int = 0) -> list[tuple[int, float]]:
    """PPO on the task reward over skills (or primitives); the success curve ``[(env steps, success)]``."""
    envs = HouseholdBatch(env, cfg.num_envs, episode_length, seed, task=task)
    options = SkillOptions(agent) if agent is not None else None
    actions = options.count if options else envs.actions
    features = int(sum(envs.sizes))
    ppo = PPOAgent(features, ActionSpec("categorical", actions),
                   PPOConfig(lr=cfg.lr, gamma=cfg.gamma, entropy_coef=cfg.entropy_coef, hidden=(64, 64)), seed=seed)
    steps, curve = 0, []
    while steps < cfg.env_steps:
        batch, taken, successes, episodes = _rollout(ppo, agent, options, envs, cfg.decisions, cfg.end_on_target)
        ppo.update(batch)
        steps += taken
        curve.append((steps, successes / episodes if episodes else float("nan")))
    return curve


def _rollout(ppo: PPOAgent, agent: SkiLDAgent | None, options: SkillOptions | None, envs: HouseholdBatch,
             decisions: int, end_on_target: bool) -> tuple[RolloutBatch, int, int, int]:
    n = len(envs.envs)
    obs, acts, logps, values, rewards, dones = [], [], [], [], [], []
    taken = successes = episodes = 0
    for _ in range(decisions):
        x = one_hot_states(envs.states, envs.sizes)
        step = ppo.policy_step(x)
        reward, done, used, won = _execute(agent, options, envs, np.asarray(step.env_actions, dtype=np.int64),
                                           end_on_target)
        taken, successes, episodes = taken + used, successes + won, episodes + int(done.sum())
        obs.append(x), acts.append(step.actions), logps.append(step.log_probs), values.append(step.values)
        rewards.append(torch.as_tensor(reward, dtype=torch.float32)), dones.append(torch.as_tensor(done))
    last = one_hot_states(envs.states, envs.sizes)
    batch = RolloutBatch(torch.stack(obs), torch.stack(acts), torch.stack(logps), torch.stack(values),
                         torch.stack(rewards), torch.stack(dones), last)
    assert batch.rewards.shape == (decisions, n)
    return batch, taken, successes, episodes


def _execute(agent: SkiLDAgent | None, options: SkillOptions | None, envs: HouseholdBatch,
             chosen: np.ndarray, end_on_target: bool = False) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Run one decision in every env: a primitive, or a skill for up to ``L`` steps (with
    ``end_on_target``, until it induces its target). Returns ``(reward sum, episode ended, env steps
    taken, successes)``."""
    n = len(envs.envs)
    reward, ended, stopped = np.zeros(n), np.zeros(n, bool), np.zeros(n, bool)
    if agent is None:
        _, _, terminated, done, _, r = envs.step(chosen)
        return r, done, n, int(terminated.sum())
    factor, row, b = options.skills(chosen)
    used = won = 0
    for _ in range(agent.cfg.skill_steps):
        active = ~(ended | stopped)
        if not active.any():
            break
        primitive = agent.act(envs.states, factor, row, b, epsilon=0.0)
        _, graphs, terminated, done, _, r = envs.step(primitive, only=active)
        if end_on_target and agent.mode == "skild":
            stopped |= active & graph_matches(object_graphs(graphs, envs.objects), factor, row)
        reward += np.where(active, r, 0.0)
        won += int((terminated & active).sum())
        ended |= done & active
        used += int(active.sum())
    return reward, ended, used, won
