"""Proximal Policy Optimisation (clipped surrogate, GAE, minibatch epochs) behind an input mask.

Discrete actions use a categorical policy; continuous actions a diagonal Gaussian whose sample is
either clipped to the action bounds or tanh-squashed into them. The batch keeps the *raw* sample,
so the likelihood ratio is exact in both cases (the squashing Jacobian cancels in the ratio).

Defaults follow ELDEN's released PPO (lr 1e-4, clip 0.1, GAE lambda 0.98, no entropy bonus,
minibatch 32, 20 envs x 600 steps), except gamma: ELDEN uses 1 on its -1-per-step household tasks,
we default to 0.99, which suits tasks without that structure.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical, Distribution, Independent, Normal

from causal.rl.base import ActionSpec, RolloutBatch, as_batch, on_device
from causal.rl.networks import InputMask, mlp


@dataclass(frozen=True)
class PPOConfig:
    """Hyper-parameters of PPO and of the rollouts that feed it."""

    lr: float = 1e-4
    gamma: float = 0.99
    """Discount (ELDEN: 1.0 on its episodic -1-per-step tasks)."""
    gae_lambda: float = 0.98
    clip: float = 0.1
    """Clip range epsilon of the surrogate ratio."""
    epochs: int = 4
    """Passes over each rollout."""
    minibatch_size: int = 32
    value_coef: float = 0.5
    entropy_coef: float = 0.0
    """Entropy bonus weight; ELDEN uses none."""
    max_grad_norm: float = 0.5
    normalize_advantages: bool = True
    hidden: tuple[int, ...] = (64, 64)
    squash: str = "clip"
    """Continuous actions: ``clip`` the Gaussian sample to the bounds or ``tanh``-squash it into them."""
    init_log_std: float = 0.0
    num_envs: int = 20
    """Parallel environments per rollout (read by the loop that collects, not by the update)."""
    rollout_steps: int = 600
    """Steps per environment per rollout (read by the loop that collects)."""

    def __post_init__(self) -> None:
        if self.squash not in ("clip", "tanh"):
            raise ValueError(f"squash must be 'clip' or 'tanh', got {self.squash!r}")


@dataclass(frozen=True)
class PolicyStep:
    """What acting produces: env-ready actions and what the batch must remember about them."""

    env_actions: np.ndarray
    actions: torch.Tensor
    log_probs: torch.Tensor
    values: torch.Tensor


def gae(rewards: torch.Tensor, values: torch.Tensor, dones: torch.Tensor, last_values: torch.Tensor,
        gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimates and value targets, both ``[T, N]``.

    ``dones[t]`` stops bootstrapping from step t to t + 1; ``last_values`` bootstraps past the end.
    """
    advantages = torch.zeros_like(rewards)
    running = torch.zeros_like(last_values)
    next_values = last_values
    for t in reversed(range(rewards.shape[0])):
        alive = 1.0 - dones[t].float()
        delta = rewards[t] + gamma * next_values * alive - values[t]
        running = delta + gamma * lam * alive * running
        advantages[t] = running
        next_values = values[t]
    return advantages, advantages + values


class ActorCritic(nn.Module):
    """Separate tanh MLPs for the policy and the value, both behind the same input mask."""

    def __init__(self, obs_dim: int, action: ActionSpec, cfg: PPOConfig,
                 input_mask: np.ndarray | Sequence[bool] | None = None) -> None:
        super().__init__()
        self.action = action
        self.input_mask = InputMask(obs_dim, input_mask)
        self.actor = mlp(obs_dim, cfg.hidden, action.size, nn.Tanh, out_gain=0.01)
        self.critic = mlp(obs_dim, cfg.hidden, 1, nn.Tanh, out_gain=1.0)
        if action.kind == "continuous":
            self.log_std = nn.Parameter(torch.full((action.size,), cfg.init_log_std))

    def distribution(self, obs: torch.Tensor) -> Distribution:
        out = self.actor(self.input_mask(obs))
        if self.action.kind == "categorical":
            return Categorical(logits=out)
        return Independent(Normal(out, self.log_std.exp().expand_as(out)), 1)

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(self.input_mask(obs)).squeeze(-1)


class PPOAgent:
    """PPO on one :class:`ActorCritic`; implements :class:`causal.rl.base.Agent`.

    Parameters are initialised from ``torch.manual_seed(seed)``; sampling and minibatch order use a
    private generator seeded with ``seed``, so a seeded run repeats exactly.
    """

    def __init__(self, obs_dim: int, action: ActionSpec, cfg: PPOConfig = PPOConfig(), seed: int = 0,
                 input_mask: np.ndarray | Sequence[bool] | None = None) -> None:
        torch.manual_seed(seed)
        self.cfg, self.action = cfg, action
        self.net = ActorCritic(obs_dim, action, cfg, input_mask)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=cfg.lr, eps=1e-5)
        self.generator = torch.Generator().manual_seed(seed)
        """On the CPU whatever the device: the same draws on any device."""
        self.device = torch.device("cpu")
        self.version = 0

    def to(self, device: torch.device) -> None:
        """Learn on ``device`` (before the first update). Inputs may come on the CPU; what the agent
        returns (actions, values, :class:`PolicyStep`) is on the CPU."""
        self.net.to(device)
        self.device = device

    def set_input_mask(self, mask: np.ndarray | Sequence[bool] | None) -> None:
        """Apply a new abstraction to the policy input (None switches masking off)."""
        self.net.input_mask.set(mask)

    @torch.no_grad()
    def policy_step(self, obs: np.ndarray | torch.Tensor, deterministic: bool = False) -> PolicyStep:
        """Sample (or take the mode of) the policy for observations ``[B, obs_dim]``."""
        x = as_batch(obs)[0].to(self.device)
        dist = self.net.distribution(x)
        actions = self._mode(dist) if deterministic else self._sample(dist)
        log_probs, values = dist.log_prob(actions).cpu(), self.net.value(x).cpu()
        actions = actions.cpu()
        return PolicyStep(self.to_env_actions(actions), actions, log_probs, values)

    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Env-ready actions for ``[B, obs_dim]`` observations, or one action for one observation."""
        _, single = as_batch(obs)
        actions = self.policy_step(obs, deterministic).env_actions
        return actions[0] if single else actions

    @torch.no_grad()
    def value(self, obs: np.ndarray | torch.Tensor) -> np.ndarray:
        """State values ``[B]``."""
        return self.net.value(as_batch(obs)[0].to(self.device)).cpu().numpy()

    def to_env_actions(self, actions: torch.Tensor) -> np.ndarray:
        """Raw sampled actions -> what the environment takes (indices, or bounded vectors)."""
        if self.action.kind == "categorical":
            return actions.numpy().astype(np.int64)
        low, high = np.array(self.action.low, np.float32), np.array(self.action.high, np.float32)
        raw = actions.numpy()
        if self.cfg.squash == "tanh":
            return (low + (np.tanh(raw) + 1.0) * 0.5 * (high - low)).astype(np.float32)
        return np.clip(raw, low, high).astype(np.float32)

    def update(self, batch: RolloutBatch) -> dict[str, float]:
        """``cfg.epochs`` passes of clipped-surrogate minibatch steps over one rollout."""
        batch = on_device(batch, self.device)
        with torch.no_grad():
            last_values = self.net.value(batch.last_obs)
        advantages, returns = gae(batch.rewards, batch.values, batch.dones, last_values,
                                  self.cfg.gamma, self.cfg.gae_lambda)
        if self.cfg.normalize_advantages:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        flat = [t.flatten(0, 1) for t in (batch.obs, batch.actions, batch.log_probs, advantages, returns)]
        totals: dict[str, float] = {}
        steps = 0
        for _ in range(self.cfg.epochs):
            order = torch.randperm(flat[0].shape[0], generator=self.generator).to(self.device)
            for index in order.split(self.cfg.minibatch_size):
                for key, value in self._minibatch_step(*(t[index] for t in flat)).items():
                    totals[key] = totals.get(key, 0.0) + value
                steps += 1
        self.version += 1
        return {key: value / max(steps, 1) for key, value in totals.items()}

    def _minibatch_step(self, obs: torch.Tensor, actions: torch.Tensor, old_log_probs: torch.Tensor,
                        advantages: torch.Tensor, returns: torch.Tensor) -> dict[str, float]:
        dist = self.net.distribution(obs)
        log_ratio = dist.log_prob(actions) - old_log_probs
        ratio = log_ratio.exp()
        clipped = ratio.clamp(1.0 - self.cfg.clip, 1.0 + self.cfg.clip)
        policy_loss = -torch.minimum(ratio * advantages, clipped * advantages).mean()
        value_loss = 0.5 * (self.net.value(obs) - returns).square().mean()
        entropy = dist.entropy().mean()
        loss = policy_loss + self.cfg.value_coef * value_loss - self.cfg.entropy_coef * entropy
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.net.parameters(), self.cfg.max_grad_norm)
        self.optimizer.step()
        with torch.no_grad():
            approx_kl = ((ratio - 1.0) - log_ratio).mean()
            clip_fraction = ((ratio - 1.0).abs() > self.cfg.clip).float().mean()
        return {"policy_loss": policy_loss.item(), "value_loss": value_loss.item(), "entropy": entropy.item(),
                "approx_kl": float(approx_kl), "clip_fraction": float(clip_fraction)}

    def _sample(self, dist: Distribution) -> torch.Tensor:
        if isinstance(dist, Categorical):
            return torch.multinomial(dist.probs.cpu(), 1, generator=self.generator).squeeze(-1).to(self.device)
        base = dist.base_dist
        return base.loc + base.scale * torch.randn(base.loc.shape, generator=self.generator).to(self.device)

    @staticmethod
    def _mode(dist: Distribution) -> torch.Tensor:
        return dist.probs.argmax(-1) if isinstance(dist, Categorical) else dist.base_dist.loc

    def state_dict(self) -> dict[str, Any]:
        """Network, optimiser, sampling generator and version."""
        return {"net": self.net.state_dict(), "optimizer": self.optimizer.state_dict(),
                "generator": self.generator.get_state(), "version": self.version}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        self.version = int(state["version"])
