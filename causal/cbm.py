"""Causal Bisimulation Modeling (dissertation ch. 4): the model and its trainer.

:class:`CBMModel` holds the dynamics (implicit by default, :mod:`causal.cbm_implicit`; or CDL's
explicit model under the same masks, for the chapter's implicit-vs-explicit comparison) and the causal
reward model (:mod:`causal.cbm_reward`). Both travel in one set of weights, so the graph-evaluator
estimates the dynamics graph and the reward's parents from the same published model, and derives the
minimal task abstraction from the two (Theorem 4.1, :func:`causal.abstraction.minimal_abstraction`).

:class:`CBMTrainer` takes one Adam step on both per update (Algorithm 5, line 7): eq. 4.4 for the
implicit dynamics (or eq. 3.3 for the explicit one), and the reward likelihood under the full and
every drop-one mask.
"""
from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from torch import nn

from causal.abstraction import with_self_edges
from causal.cbm_config import CBMConfig
from causal.cbm_implicit import ImplicitDynamics
from causal.cbm_reward import CausalRewardModel
from causal.cdl import CDLModel
from causal.factored import FactorLayout
from causal.method import layout_from_config, model_config_json


class CBMModel(nn.Module):
    """CBM's dynamics model (``dynamics``) and causal reward model (``reward``) for one factor layout."""

    def __init__(self, layout: FactorLayout, cfg: CBMConfig) -> None:
        super().__init__()
        self.layout, self.cfg = layout, cfg
        self.dynamics: ImplicitDynamics | CDLModel = (
            ImplicitDynamics(layout, cfg) if cfg.dynamics == "implicit" else CDLModel(layout, cfg.cdl()))
        self.reward = CausalRewardModel(layout, cfg)

    @property
    def implicit(self) -> bool:
        return isinstance(self.dynamics, ImplicitDynamics)

    @torch.no_grad()
    def dynamics_cmi(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                     generator: torch.Generator | None = None, num_negatives: int | None = None,
                     max_samples: int | None = None) -> torch.Tensor:
        """``[d_S, d_S + 1]`` CMI of the dynamics, nats: eq. 4.3 on at most ``max_samples`` (default
        ``cmi_samples``) of these transitions with ``num_negatives`` (default ``eval_negatives``)
        negatives (implicit), or CDL's eq. 3.2 on all of them (explicit)."""
        if not self.implicit:
            return self.dynamics.cmi(state, action, next_state)
        limit = max_samples or self.cfg.cmi_samples
        if state.shape[0] > limit:
            index = torch.randperm(state.shape[0], generator=generator)[:limit]
            state, action, next_state = state[index], action[index], next_state[index]
        return self.dynamics.cmi(state, action, next_state, num_negatives or self.cfg.eval_negatives, generator)

    @torch.no_grad()
    def reward_cmi(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        """``[d_S + 1]`` reward CMI per factor at t and the action (last), nats."""
        return self.reward.cmi(state, action, reward)


def model_from_config(data: dict[str, Any]) -> CBMModel:
    """An untrained CBMModel from a parsed :meth:`CBMTrainer.config_json`."""
    if data.get("model") != "cbm":
        raise ValueError(f"not a CBM model config: {data.get('model')!r}")
    return CBMModel(layout_from_config(data), CBMConfig(**data["cbm"]))


class CBMTrainer:
    """Owns a CBMModel, its optimiser, the parents of the causal term and the delta range's state."""

    def __init__(self, layout: FactorLayout, cfg: CBMConfig, seed: int = 0) -> None:
        torch.manual_seed(seed)
        self.cfg = cfg
        self.model = CBMModel(layout, cfg)
        trainable = [p for p in self.model.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(trainable, lr=cfg.lr, fused=True)
        self.generator = torch.Generator().manual_seed(seed)
        n = layout.num_factors
        self.parents = torch.ones(n, n + 1, dtype=torch.bool)
        self.updates = 0
        self.range_seen = False
        """Whether the implicit model's delta range has been set from data (it widens with every batch)."""
        self.nonfinite = 0
        """Updates in a row skipped for a non-finite loss or gradient (reported as ``nonfinite_loss``, as CDL's)."""

    def set_parents(self, adjacency: np.ndarray) -> None:
        """Parents PA(S^j) for the causal term, from the evaluator's graph ``[d_S, d_S + 1]``."""
        if adjacency.shape != tuple(self.parents.shape):
            raise ValueError(f"adjacency shape {adjacency.shape} != {tuple(self.parents.shape)}")
        self.parents = torch.from_numpy(with_self_edges(adjacency))

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
               reward: torch.Tensor | None = None) -> dict[str, float]:
        """One Adam step on the dynamics loss and, given rewards, the reward model's; returns the mean
        loss of each term in nats per factor (``nll_*``: InfoNCE for implicit dynamics)."""
        causal = self.updates % self.cfg.causal_every == 0
        loss, stats = self._dynamics_loss(state, action, next_state, self.parents if causal else None)
        if reward is not None:
            errors = self.model.reward.squared_errors(state, action, reward)
            loss = loss + errors.mean(dim=1).sum()
            nll = self.model.reward.nll(errors.detach())
            stats["nll_reward"], stats["nll_reward_masked"] = float(nll[0]), float(nll[1:].mean())
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
        if not (torch.isfinite(loss) and torch.isfinite(norm)):
            self.nonfinite += 1  # no step: non-finite values never reach the parameters
            return {"nonfinite_loss": float(self.nonfinite)}
        self.nonfinite = 0
        self.optimizer.step()
        self.updates += 1
        return stats

    def _dynamics_loss(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                       parents: torch.Tensor | None) -> tuple[torch.Tensor, dict[str, float]]:
        dynamics = self.model.dynamics
        if isinstance(dynamics, ImplicitDynamics):
            if dynamics.codec.cont_factors:
                dynamics.observe_labels(state, next_state, first=not self.range_seen)
                self.range_seen = True
            nce, reg = dynamics.training_losses(state, action, next_state, parents, self.generator)
            per_term, loss = nce.detach().mean(dim=(0, 2)), (nce + reg).mean(dim=2).sum()
        else:
            nll = dynamics.training_nll(state, action, next_state, parents, self.generator)
            per_term, loss = nll.detach().mean(dim=(0, 2)), nll.mean(dim=2).sum()
        stats = {"nll_full": float(per_term[0]), "nll_masked": float(per_term[1])}
        if parents is not None:
            stats["nll_causal"] = float(per_term[2])
        return loss, stats

    @property
    def batch_size(self) -> int:
        return self.cfg.batch_size

    @property
    def lr(self) -> float:
        return self.cfg.lr

    def config_json(self) -> str:
        return model_config_json("cbm", self.model.layout, self.cfg)

    def state_dict(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "parents": self.parents.clone(), "updates": self.updates, "range_seen": self.range_seen,
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        state = copy.deepcopy(state)  # the optimiser would otherwise alias the source's moment tensors
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.parents = state["parents"].to(torch.bool)
        self.updates, self.range_seen = int(state["updates"]), bool(state["range_seen"])
        self.generator.set_state(state["generator"])
