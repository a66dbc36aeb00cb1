"""Soft Actor-Critic for categorical actions (Christodoulou 2019): SAC where the policy is a softmax.

With finitely many actions the expectations SAC samples are exact sums over the actions: the critics
output one Q per action, the soft value is ``sum_a pi(a|s) (min Q(s, a) - alpha log pi(a|s))``, and
the actor minimises ``sum_a pi(a|s) (alpha log pi(a|s) - min Q(s, a))``. Everything else is
:mod:`causal.rl.sac`'s: twin critics with Polyak targets, automatic temperature, the same
:class:`SACConfig`, and the actor and both critics reading the observation through one input mask,
which is how CBM's policy sees only its task abstraction on an environment with discrete actions
(Chemical). The target entropy defaults to half the uniform policy's, ``0.5 log |A|``.
"""
from __future__ import annotations

import copy
import math
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from causal.rl.base import ActionSpec, ReplayBatch, as_batch
from causal.rl.networks import InputMask, mlp
from causal.rl.sac import SACConfig


class DiscreteSACAgent:
    """SAC over ``action.size`` categories; implements :class:`causal.rl.base.Agent`. ``act`` returns
    category indices; ``update`` reads the index from the first column of ``batch.actions``.
    Parameters come from ``torch.manual_seed(seed)``, action sampling from a generator seeded ``seed``."""

    def __init__(self, obs_dim: int, action: ActionSpec, cfg: SACConfig = SACConfig(), seed: int = 0,
                 input_mask: np.ndarray | Sequence[bool] | None = None) -> None:
        if action.kind != "categorical":
            raise ValueError("DiscreteSACAgent is for categorical actions")
        torch.manual_seed(seed)
        self.cfg, self.action = cfg, action
        self.input_mask = InputMask(obs_dim, input_mask)
        self.actor = mlp(obs_dim, cfg.hidden, action.size)
        self.critic = torch.nn.ModuleList([mlp(obs_dim, cfg.hidden, action.size) for _ in range(2)])
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(cfg.init_alpha), requires_grad=True)
        default_target = 0.5 * math.log(action.size)
        self.target_entropy = default_target if cfg.target_entropy is None else cfg.target_entropy
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.lr)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=cfg.lr)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=cfg.lr)
        self.generator = torch.Generator().manual_seed(seed)
        self.version = 0

    @property
    def alpha(self) -> float:
        return self.log_alpha.detach().exp().item()

    def set_input_mask(self, mask: np.ndarray | Sequence[bool] | None) -> None:
        """Apply a new abstraction to the actor and the critics (None switches masking off)."""
        self.input_mask.set(mask)

    def log_policy(self, obs: torch.Tensor) -> torch.Tensor:
        """``log pi(a | masked obs)`` for every action, ``[B, |A|]``."""
        return F.log_softmax(self.actor(self.input_mask(obs)), dim=-1)

    def q_values(self, obs: torch.Tensor, target: bool = False) -> torch.Tensor:
        """``min(Q1, Q2)`` of the (target) critics for every action, ``[B, |A|]``."""
        critic, x = (self.target_critic if target else self.critic), self.input_mask(obs)
        return torch.minimum(critic[0](x), critic[1](x))

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Category indices ``[B]`` for ``[B, obs_dim]`` observations (a scalar array for one)."""
        x, single = as_batch(obs)
        log_pi = self.log_policy(x)
        if deterministic:
            actions = log_pi.argmax(-1)
        else:
            actions = torch.multinomial(log_pi.exp(), 1, generator=self.generator).squeeze(-1)
        out = actions.numpy()
        return out[0] if single else out

    def update(self, batch: ReplayBatch) -> dict[str, float]:
        """One gradient step each for the critics, the actor and the temperature; then Polyak."""
        stats = self._critic_step(batch)
        stats.update(self._actor_and_alpha_step(batch.obs))
        with torch.no_grad():
            for target, source in zip(self.target_critic.parameters(), self.critic.parameters()):
                target.lerp_(source, self.cfg.tau)
        self.version += 1
        return stats

    def _critic_step(self, batch: ReplayBatch) -> dict[str, float]:
        with torch.no_grad():
            log_pi = self.log_policy(batch.next_obs)
            soft = (log_pi.exp() * (self.q_values(batch.next_obs, target=True) - self.alpha * log_pi)).sum(-1)
            target = batch.rewards + self.cfg.gamma * (1.0 - batch.terminated) * soft
        index = batch.actions[:, :1].long()
        x = self.input_mask(batch.obs)
        q1, q2 = (critic(x).gather(1, index).squeeze(1) for critic in self.critic)
        loss = 0.5 * ((q1 - target).square().mean() + (q2 - target).square().mean())
        self.critic_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_optimizer.step()
        return {"critic_loss": loss.item(), "q_mean": q1.mean().item()}

    def _actor_and_alpha_step(self, obs: torch.Tensor) -> dict[str, float]:
        log_pi = self.log_policy(obs)
        pi = log_pi.exp()
        with torch.no_grad():
            q = self.q_values(obs)
        actor_loss = (pi * (self.alpha * log_pi - q)).sum(-1).mean()
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optimizer.step()
        entropy = -(pi * log_pi).sum(-1).detach()
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
