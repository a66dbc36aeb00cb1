"""Training ELDEN's ensemble: eqs. 5.2-5.3 with Mixup for discrete factors, each member on its own
share of the batch, and the prediction-error priorities of the rows it was given (chapter 5's
prioritised dynamics replay).

The learner hands over ``members x member_batch`` rows; row ``k`` goes to member ``k // member_batch``.
Mixup (Zhang et al. 2018, chapter 5's "Implementation Details") pairs each row with another of the
same member's share and mixes inputs, action and next-state labels with a weight ~ Beta(0.1, 0.1).
"""
from __future__ import annotations

import copy
import json
from typing import Any

import numpy as np
import torch

from causal.elden import ELDENConfig, ELDENModel, Targets
from causal.factored import FactorLayout
from causal.method import model_config_json


def mixup(x: torch.Tensor, targets: Targets, weights: torch.Tensor,
          partner: torch.Tensor) -> tuple[torch.Tensor, Targets]:
    """Rows mixed with their partners: ``w * row + (1 - w) * partner``, for inputs ``x`` [M, B, T, W]
    and every target (soft labels, current and next continuous values); ``weights`` and ``partner``
    are [M, B] (a partner is a row index within the same member's share)."""
    def mix(t: torch.Tensor) -> torch.Tensor:
        other = torch.gather(t, 1, partner.view(*partner.shape, *([1] * (t.dim() - 2))).expand_as(t))
        w = weights.view(*weights.shape, *([1] * (t.dim() - 2)))
        return w * t + (1 - w) * other
    return mix(x), Targets(*(mix(t) for t in targets))


class ELDENTrainer:
    """Owns an ELDENModel, its optimiser and the random state of Mixup; the dynamics-learner's trainer."""

    def __init__(self, layout: FactorLayout, cfg: ELDENConfig, seed: int = 0) -> None:
        torch.manual_seed(seed)
        self.cfg = cfg
        self.model = self.build_model(layout, cfg)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.rng = np.random.default_rng(seed)
        self.updates = 0
        self.last_priorities: np.ndarray | None = None
        """Replay priorities of the rows of the last update, in the order given (``None`` unless
        ``cfg.prioritised``): ``(1 - exp(-error))^priority_alpha`` of the row's member."""
        discrete = bool(layout.categorical) or layout.action_kind == "categorical"
        self.uses_mixup = cfg.mixup and discrete

    def build_model(self, layout: FactorLayout, cfg: ELDENConfig) -> ELDENModel:
        """The model this trainer trains (a subclass may train a variant of ELDEN's network)."""
        return ELDENModel(layout, cfg)

    @property
    def batch_size(self) -> int:
        return self.cfg.batch_size

    @property
    def lr(self) -> float:
        return self.cfg.lr

    def split(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> tuple[torch.Tensor, Targets]:
        """A learner batch -> each member's encoded inputs [M, b, T, W] and targets [M, b, ...]."""
        m = self.cfg.members
        x = self.model.encode(state, action)
        targets = self.model.targets(state, next_state)
        return x.unflatten(0, (m, -1)), Targets(*(t.unflatten(0, (m, -1)) for t in targets))

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        """One Adam step on eq. 5.3 for every member; returns the mean NLL per factor and the regulariser."""
        x, targets = self.split(state, action, next_state)
        if self.cfg.prioritised:
            self.last_priorities = self.priorities(x, targets)
        if self.uses_mixup:
            x, targets = mixup(x, targets, *self._mixup_draw(x.shape[0], x.shape[1]))
        nll = -self.model.log_likelihood(self.model(x), targets)
        loss = nll.mean(dim=1).sum()
        stats = {"nll_full": float(nll.detach().mean())}
        if self.cfg.grad_reg > 0:
            rows = self.cfg.grad_reg_rows or x.shape[1]
            sub = x[:, :rows].detach().requires_grad_(True)
            penalty = self.gradient_penalty(self.model(sub), sub, Targets(*(t[:, :rows] for t in targets)))
            loss = loss + self.cfg.grad_reg * penalty
            stats["grad_penalty"] = float(penalty.detach()) / self.cfg.members
        return self.step(loss, stats)

    def step(self, loss: torch.Tensor, stats: dict[str, float]) -> dict[str, float]:
        """One Adam step on ``loss`` (gradient-norm clipped), counted; returns ``stats``."""
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
        self.optimizer.step()
        self.updates += 1
        return stats

    def gradient_penalty(self, out: torch.Tensor, x: torch.Tensor, targets: Targets) -> torch.Tensor:
        """``sum_ij |d p(s^j_t+1) / d s^i_t|`` of eqs. 5.2-5.3 for outputs ``out`` of inputs ``x`` (which
        require grad), averaged over each member's rows and summed over members, estimated with one
        output ``j`` per row drawn uniformly (times ``d_S``): unbiased for the sum over outputs, at the
        cost of one extra backward pass instead of ``d_S``. The trainer estimates it on the first
        ``grad_reg_rows`` rows of each member's (random) share.
        Inputs are reduced per variable as the local graphs are (:meth:`ELDENModel.reduce_inputs`)."""
        outputs = self.model.num_outputs
        chosen = torch.from_numpy(self.rng.integers(0, outputs, out.shape[:2]))
        quantity = self.model.graph_quantity(out, targets).gather(-1, chosen[..., None])
        (grad,) = torch.autograd.grad(quantity.sum(), x, create_graph=True)
        return outputs * self.model.reduce_inputs(grad, x).sum(dim=-1).mean(dim=1).sum()

    def _mixup_draw(self, members: int, rows: int) -> tuple[torch.Tensor, torch.Tensor]:
        alpha = self.cfg.mixup_alpha
        weights = torch.from_numpy(self.rng.beta(alpha, alpha, (members, rows)).astype(np.float32))
        partner = torch.from_numpy(np.argsort(self.rng.random((members, rows)), axis=1))
        return weights, partner

    @torch.no_grad()
    def priorities(self, x: torch.Tensor, targets: Targets) -> np.ndarray:
        """``(1 - exp(-error))^alpha`` per row (flattened member-major), the error summed over factors
        (:meth:`ELDENModel.prediction_error`: cross-entropy, or half the squared error of a continuous
        factor's mean)."""
        error = self.model.prediction_error(self.model(x), targets).sum(dim=-1)
        return (-torch.expm1(-error)).clamp_min(1e-6).pow(self.cfg.priority_alpha).flatten().numpy()

    def set_parents(self, adjacency: np.ndarray) -> None:
        """ELDEN publishes no global graph, so it never gets one back."""

    def config_json(self) -> str:
        return model_config_json("elden", self.model.layout, self.cfg)

    def state_dict(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(), "updates": self.updates,
                "rng": torch.from_numpy(np.frombuffer(_rng_bytes(self.rng), dtype=np.uint8).copy())}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        state = copy.deepcopy(state)
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state["updates"])
        self.rng = _rng_from_bytes(state["rng"].numpy().tobytes())


def _rng_bytes(rng: np.random.Generator) -> bytes:
    """A numpy generator's state as bytes (checkpoints hold tensors only: ``weights_only`` loading)."""
    return json.dumps(rng.bit_generator.state).encode()


def _rng_from_bytes(data: bytes) -> np.random.Generator:
    rng = np.random.default_rng()
    rng.bit_generator.state = json.loads(data.decode())
    return rng
