"""Soft Actor-Critic for continuous actions (twin Q, Polyak targets, automatic entropy tuning).

The actor and both critics read the observation through the same input mask, which is how CBM
runs "SAC on the masked observation" of its task abstraction. Defaults follow the CBM reference
([256, 256], lr 1e-4, tau 0.005, gamma 0.99, batch 256); the target entropy is -|A|.
"""
from __future__ import annotations

import copy
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from causal.rl.base import ActionSpec, ReplayBatch, as_batch, on_device
from causal.rl.networks import InputMask, mlp


@dataclass(frozen=True)
class SACConfig:
    """Hyper-parameters of SAC."""

    hidden: tuple[int, ...] = (256, 256)
    lr: float = 1e-4
    """Learning rate of the actor, the critics and the temperature."""
    tau: float = 0.005
    """Polyak rate of the target critics."""
    gamma: float = 0.99
    batch_size: int = 256
    """Rows per update (read by the loop that samples the replay)."""
    init_alpha: float = 1.0
    target_entropy: float | None = None
    """Entropy target of the temperature; None = -(action dimensions)."""
    log_std_min: float = -5.0
    log_std_max: float = 2.0


class SquashedGaussianActor(nn.Module):
    """A tanh-squashed Gaussian policy scaled into the action bounds."""

    def __init__(self, obs_dim: int, action: ActionSpec, cfg: SACConfig, input_mask: InputMask) -> None:
        super().__init__()
        self.input_mask, self.cfg = input_mask, cfg
        self.body = mlp(obs_dim, cfg.hidden, 2 * action.size)
        low, high = torch.tensor(action.low), torch.tensor(action.high)
        self.register_buffer("center", (high + low) / 2)
        self.register_buffer("half_range", (high - low) / 2)

    def forward(self, obs: torch.Tensor, deterministic: bool = False,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Actions in the env's bounds and their log-probabilities ``[B]``."""
        mean, log_std = self.body(self.input_mask(obs)).chunk(2, dim=-1)
        log_std = log_std.clamp(self.cfg.log_std_min, self.cfg.log_std_max)
        noise = torch.zeros_like(mean) if deterministic else torch.randn(mean.shape, generator=generator).to(mean.device)
        raw = mean + log_std.exp() * noise
        log_prob = (-0.5 * noise.square() - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
        # log(1 - tanh(u)^2) in a stable form, plus the affine scaling into the bounds.
        log_prob -= (2 * (math.log(2) - raw - F.softplus(-2 * raw)) + self.half_range.log()).sum(-1)
        return self.center + self.half_range * torch.tanh(raw), log_prob


class TwinQ(nn.Module):
    """Two independent Q networks on (masked observation, action scaled to [-1, 1])."""

    def __init__(self, obs_dim: int, action: ActionSpec, cfg: SACConfig, input_mask: InputMask) -> None:
        super().__init__()
        self.input_mask = input_mask
        self.q1 = mlp(obs_dim + action.size, cfg.hidden, 1)
        self.q2 = mlp(obs_dim + action.size, cfg.hidden, 1)
        low, high = torch.tensor(action.low), torch.tensor(action.high)
        self.register_buffer("center", (high + low) / 2)
        self.register_buffer("half_range", (high - low) / 2)

    def forward(self, obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([self.input_mask(obs), (actions - self.center) / self.half_range], dim=-1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


class SoftActorCritic(ABC):
    """What both SACs share: twin critics with Polyak targets, automatic temperature, the update order
    (critics, then actor and temperature, then Polyak), device moves and checkpoints.

    A subclass builds ``actor`` and ``critic`` (and ``input_mask``), calls :meth:`_init_learning`, and
    supplies the three places where continuous and categorical SAC differ: the soft value of the next
    observation, the critics' value of the taken action, and the actor's loss with the per-sample
    entropy the temperature is tuned on.
    """

    cfg: SACConfig
    actor: nn.Module
    critic: nn.Module

    def _init_learning(self, target_entropy: float) -> None:
        cfg = self.cfg
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(cfg.init_alpha), requires_grad=True)
        self.target_entropy = target_entropy if cfg.target_entropy is None else cfg.target_entropy
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.lr)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=cfg.lr)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=cfg.lr)
        self.device = torch.device("cpu")
        self.version = 0

    def to(self, device: torch.device) -> None:
        """Learn on ``device`` (before the first update; the temperature's optimiser is made anew).
        Inputs may come on the CPU; actions are returned on the CPU."""
        for module in (self.actor, self.critic, self.target_critic):
            module.to(device)
        self.log_alpha = self.log_alpha.detach().to(device).requires_grad_(True)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=self.cfg.lr)
        self.device = device

    @property
    def alpha(self) -> float:
        return self.log_alpha.detach().exp().item()

    def update(self, batch: ReplayBatch) -> dict[str, float]:
        """One gradient step each for the critics, the actor and the temperature; then Polyak."""
        batch = on_device(batch, self.device)
        stats = self._critic_step(batch)
        stats.update(self._actor_and_alpha_step(batch.obs))
        with torch.no_grad():
            for target, source in zip(self.target_critic.parameters(), self.critic.parameters()):
                target.lerp_(source, self.cfg.tau)
        self.version += 1
        return stats

    @abstractmethod
    def _soft_value(self, next_obs: torch.Tensor) -> torch.Tensor:
        """``V(s') = E_a' [min Q_target(s', a') - alpha log pi(a' | s')]``, ``[B]`` (under no_grad)."""

    @abstractmethod
    def _taken_q(self, batch: ReplayBatch) -> tuple[torch.Tensor, torch.Tensor]:
        """Both critics' values of the batch's actions, ``[B]`` each."""

    @abstractmethod
    def _actor_loss(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The actor's loss and the per-sample entropy (estimate) the temperature is tuned on."""

    def _critic_step(self, batch: ReplayBatch) -> dict[str, float]:
        with torch.no_grad():
            target = batch.rewards + self.cfg.gamma * (1.0 - batch.terminated) * self._soft_value(batch.next_obs)
        q1, q2 = self._taken_q(batch)
        loss = 0.5 * ((q1 - target).square().mean() + (q2 - target).square().mean())
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_optimizer.step()
        return {"critic_loss": loss.item(), "q_mean": q1.mean().item()}

    def _actor_and_alpha_step(self, obs: torch.Tensor) -> dict[str, float]:
        actor_loss, entropy = self._actor_loss(obs)
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optimizer.step()
        entropy = entropy.detach()
        alpha_loss = (self.log_alpha * (entropy - self.target_entropy)).mean()
        self.alpha_optimizer.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_optimizer.step()
        return {"actor_loss": actor_loss.item(), "alpha": self.alpha, "entropy": entropy.mean().item()}

    def state_dict(self) -> dict[str, Any]:
        """Networks, optimisers, temperature, sampling generator and version."""
        return {"actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
                "target_critic": self.target_critic.state_dict(), "log_alpha": self.log_alpha.detach().clone(),
                "actor_optimizer": self.actor_optimizer.state_dict(),
                "critic_optimizer": self.critic_optimizer.state_dict(),
                "alpha_optimizer": self.alpha_optimizer.state_dict(),
                "generator": self.generator.get_state(), "version": self.version}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in ("actor", "critic", "target_critic", "actor_optimizer", "critic_optimizer", "alpha_optimizer"):
            getattr(self, name).load_state_dict(state[name])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.generator.set_state(state["generator"])
        self.version = int(state["version"])


class SACAgent(SoftActorCritic):
    """SAC; implements :class:`causal.rl.base.Agent` (``update`` takes a :class:`ReplayBatch`).

    Parameters are initialised from ``torch.manual_seed(seed)``; action noise uses a private
    generator seeded with ``seed``.
    """

    def __init__(self, obs_dim: int, action: ActionSpec, cfg: SACConfig = SACConfig(), seed: int = 0,
                 input_mask: np.ndarray | Sequence[bool] | None = None) -> None:
        if action.kind != "continuous":
            raise ValueError("SAC here is for continuous actions")
        torch.manual_seed(seed)
        self.cfg, self.action = cfg, action
        self.input_mask = InputMask(obs_dim, input_mask)
        self.actor = SquashedGaussianActor(obs_dim, action, cfg, self.input_mask)
        self.critic = TwinQ(obs_dim, action, cfg, self.input_mask)
        self._init_learning(target_entropy=-float(action.size))
        self.generator = torch.Generator().manual_seed(seed)

    def set_input_mask(self, mask: np.ndarray | Sequence[bool] | None) -> None:
        """Apply a new abstraction to actor and critics (None switches masking off)."""
        self.input_mask.set(mask)
        self.target_critic.input_mask.set(mask)

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Bounded actions ``[B, A]`` for ``[B, obs_dim]`` observations (``[A]`` for one)."""
        x, single = as_batch(obs)
        actions = self.actor(x.to(self.device), deterministic, self.generator)[0].cpu().numpy()
        return actions[0] if single else actions

    def _soft_value(self, next_obs: torch.Tensor) -> torch.Tensor:
        next_actions, next_log_probs = self.actor(next_obs, generator=self.generator)
        next_q = torch.minimum(*self.target_critic(next_obs, next_actions))
        return next_q - self.log_alpha.exp() * next_log_probs

    def _taken_q(self, batch: ReplayBatch) -> tuple[torch.Tensor, torch.Tensor]:
        return self.critic(batch.obs, batch.actions)

    def _actor_loss(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        actions, log_probs = self.actor(obs, generator=self.generator)
        self.critic.requires_grad_(False)  # the actor's loss must not spend time on critic gradients
        q = torch.minimum(*self.critic(obs, actions))
        self.critic.requires_grad_(True)
        return (self.log_alpha.exp().detach() * log_probs - q).mean(), -log_probs
