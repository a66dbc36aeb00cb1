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

import math
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from causal.rl.base import ActionSpec, ReplayBatch, as_batch
from causal.rl.networks import InputMask, mlp
from causal.rl.sac import SACConfig, SoftActorCritic


class DiscreteSACAgent(SoftActorCritic):
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
        self._init_learning(target_entropy=0.5 * math.log(action.size))
        self.generator = torch.Generator().manual_seed(seed)

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
        log_pi = self.log_policy(x.to(self.device))
        if deterministic:
            actions = log_pi.argmax(-1)
        else:
            actions = torch.multinomial(log_pi.exp().cpu(), 1, generator=self.generator).squeeze(-1)
        out = actions.cpu().numpy()
        return out[0] if single else out

    def _soft_value(self, next_obs: torch.Tensor) -> torch.Tensor:
        log_pi = self.log_policy(next_obs)
        return (log_pi.exp() * (self.q_values(next_obs, target=True) - self.alpha * log_pi)).sum(-1)

    def _taken_q(self, batch: ReplayBatch) -> tuple[torch.Tensor, torch.Tensor]:
        index = batch.actions[:, :1].long()
        x = self.input_mask(batch.obs)
        q1, q2 = (critic(x).gather(1, index).squeeze(1) for critic in self.critic)
        return q1, q2

    def _actor_loss(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        log_pi = self.log_policy(obs)
        pi = log_pi.exp()
        with torch.no_grad():
            q = self.q_values(obs)
        return (pi * (self.alpha * log_pi - q)).sum(-1).mean(), -(pi * log_pi).sum(-1)
