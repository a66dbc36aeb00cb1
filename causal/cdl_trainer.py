"""Training CDL: eq. 3.3 with the causal term every ``causal_every`` updates, plus checkpoint state."""
from __future__ import annotations

import copy

import numpy as np
import torch

from causal.abstraction import with_self_edges
from causal.cdl import CDLConfig, CDLModel, model_config_json
from causal.factored import FactorLayout


class CDLTrainer:
    """Owns a CDLModel, its optimiser and the parents used by the causal likelihood term."""

    def __init__(self, layout: FactorLayout, cfg: CDLConfig, seed: int = 0) -> None:
        torch.manual_seed(seed)
        self.cfg = cfg
        self.model = CDLModel(layout, cfg)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, fused=True)
        self.generator = torch.Generator().manual_seed(seed)
        n = layout.num_factors
        self.parents = torch.ones(n, n + 1, dtype=torch.bool)
        self.updates = 0
        self.nonfinite = 0
        """Updates in a row skipped for a non-finite loss or gradient (reported as ``nonfinite_loss``)."""

    def set_parents(self, adjacency: np.ndarray) -> None:
        """Parents PA(S^j) for the causal term, from a CMI graph [d_S, d_S + 1]."""
        if adjacency.shape != tuple(self.parents.shape):
            raise ValueError(f"adjacency shape {adjacency.shape} != {tuple(self.parents.shape)}")
        self.parents = torch.from_numpy(with_self_edges(adjacency)).to(self.parents.device)

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        """One gradient step on eq. 3.3; returns the mean NLL of each term (nats per factor)."""
        causal = self.updates % self.cfg.causal_every == 0
        nll = self.model.training_nll(state, action, next_state, self.parents if causal else None, self.generator)
        loss = nll.mean(dim=2).sum()
        lr = self.lr  # a function of the update count, so a resumed run continues the schedule
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        norm = torch.nn.utils.get_total_norm([p.grad for p in self.model.parameters() if p.grad is not None])
        if not (torch.isfinite(loss) and torch.isfinite(norm)):
            self.nonfinite += 1  # no step: non-finite values never reach the parameters
            return {"nonfinite_loss": float(self.nonfinite)}
        self.nonfinite = 0
        # The clip of clip_grad_norm_ (max norm / (norm + 1e-6), at most 1), applied by the fused Adam
        # step itself: it divides every gradient by ``grad_scale`` as it reads it (the protocol AMP's
        # GradScaler uses), which spares a pass over all gradients; tested equal to clip_grad_norm_
        # then Adam (tests/causal/test_cdl.py)
        self.optimizer.grad_scale = (norm + 1e-6).div(self.cfg.grad_clip).clamp(min=1.0)
        self.optimizer.step()
        self.updates += 1
        per_term = nll.detach().mean(dim=(0, 2))
        stats = {"nll_full": float(per_term[0]), "nll_masked": float(per_term[1])}
        if causal:
            stats["nll_causal"] = float(per_term[2])
        return stats

    def to(self, device: torch.device) -> None:
        """Train on ``device``: the model and the causal term's parents move there (before the first
        update; the optimiser's moments are made where the parameters are)."""
        self.model.to(device)
        self.parents = self.parents.to(device)

    @property
    def batch_size(self) -> int:
        return self.cfg.batch_size

    @property
    def lr(self) -> float:
        """The learning rate of the next update."""
        return self.cfg.lr_at(self.updates)

    def config_json(self) -> str:
        return model_config_json(self.model.layout, self.cfg)

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "parents": self.parents.clone(), "updates": self.updates,
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        state = copy.deepcopy(state)  # the optimiser would otherwise alias the source's moment tensors
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.parents = state["parents"].to(device=self.parents.device, dtype=torch.bool)
        self.updates = int(state["updates"])
        self.generator.set_state(state["generator"])
