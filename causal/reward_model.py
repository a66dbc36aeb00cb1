"""CDL's reward predictor R(phi(s_t), a_t) of eq. 3.5, learned in the abstract space.

Its inputs are the factors the abstraction keeps plus any provided extra factors (a task's goal,
e.g. the Match goal colours), each encoded as the dynamics model encodes it (one-hot colours,
normalised continuous values), and the action (one-hot, or the raw vector). The layout therefore
describes the whole observation the reward sees: the state factors followed by the extra ones.
Loss: absolute error (the chapter's choice); MLP [32, 32]; Adam lr 3e-4 (the reference).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import torch

from causal.factored import FactorCodec, FactorLayout
from causal.rl.networks import mlp


@dataclass(frozen=True)
class RewardModelConfig:
    """Architecture and optimisation of the reward predictor."""

    hidden: tuple[int, ...] = (32, 32)
    lr: float = 3e-4


class RewardModel:
    """An MLP from (kept and extra factors, action) to the reward, with its optimiser."""

    def __init__(self, layout: FactorLayout, inputs: Sequence[int], cfg: RewardModelConfig = RewardModelConfig(),
                 seed: int = 0) -> None:
        """``layout`` covers the observation (state and extra factors); ``inputs`` are the factors the
        predictor reads: ``Abstraction.kept`` plus the extra factors' indices."""
        torch.manual_seed(seed)
        self.layout, self.cfg = layout, cfg
        self.inputs = torch.tensor(sorted(set(inputs)), dtype=torch.long)
        self.codec = FactorCodec(layout)
        width = len(self.inputs) * layout.input_width + layout.action_width
        self.net = mlp(width, cfg.hidden, 1)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)

    def encode(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The predictor's input ``[B, width]`` from flat states and actions."""
        factors = self.codec.encode_state(state.to(torch.float32))[:, self.inputs].flatten(1)
        return torch.cat([factors, self.codec.encode_action(action)], dim=1)

    def predict(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Predicted rewards ``[B]`` (differentiable)."""
        return self.net(self.encode(state, action)).squeeze(-1)

    def loss(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        """Eq. 3.5 with the absolute error: mean |R(phi(s), a) - r|."""
        return (self.predict(state, action) - reward.reshape(-1)).abs().mean()

    def fit_step(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor) -> float:
        """One Adam step on a batch; returns the batch's L1 loss before the step."""
        loss = self.loss(state, action, reward)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return loss.item()

    @torch.no_grad()
    def __call__(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Predicted rewards ``[B]`` without gradients: a ``reward_fn`` for ``CEMPlanner``."""
        return self.predict(state, action)

    def state_dict(self) -> dict[str, Any]:
        return {"net": self.net.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.optimizer.load_state_dict(state["optimizer"])
