"""CBM (dissertation ch. 4) as a Causeway method: implicit dynamics with CMI for implicit models, a causal
reward model, and the minimal task abstraction (the reward's parents and their dynamics ancestors).

The parts live in :mod:`causal.cbm` (model and trainer), :mod:`causal.cbm_implicit`,
:mod:`causal.cbm_reward` and :func:`causal.abstraction.minimal_abstraction`; this module names them
for the registry. ``--cbm-dynamics explicit`` swaps in CDL's explicit model under the same masks.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import torch

from causal.abstraction import minimal_abstraction
from causal.cbm import CBMModel, CBMTrainer, model_from_config
from causal.cbm_config import CBMConfig
from causal.method import Method
from causal.planning import cdl_rollout_step
from causal.rl import abstraction_input_mask


class DynamicsCMI:
    """Global graph: CMI of every (next factor, input) pair (eq. 4.3 implicit, eq. 3.2 explicit)."""

    name = "cmi"

    def __init__(self, seed: int = 0) -> None:
        self.generator = torch.Generator().manual_seed(seed)

    def scores(self, model: CBMModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> np.ndarray:
        return model.dynamics_cmi(state, action, next_state, self.generator).numpy()

    def threshold(self, model: CBMModel) -> float:
        return model.cfg.cmi_threshold


class RewardCMI:
    """Reward graph: CMI of the reward with every factor at t and the action (Assumption 7)."""

    name = "reward_cmi"

    def scores(self, model: CBMModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
               reward: torch.Tensor) -> np.ndarray:
        return model.reward_cmi(state, action, reward).numpy()

    def threshold(self, model: CBMModel) -> float:
        return model.cfg.reward_threshold


def cbm_rollout_step(model: CBMModel, parents: torch.Tensor, factors: Sequence[int] | None = None
                     ) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """The model as a simulator in causal mode: argmax predictions (implicit) or CDL's (explicit);
    ``factors`` are rolled out, every other column held."""
    if not model.implicit:
        return cdl_rollout_step(model.dynamics, parents, factors)
    columns = None if factors is None else torch.from_numpy(abstraction_input_mask(model.layout, factors))

    def step(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        predicted = model.dynamics.predict(states, actions, parents)
        return predicted if columns is None else torch.where(columns, predicted, states)

    return step


METHOD = Method(
    name="cbm",
    title="Causal Bisimulation Modeling (ch. 4): implicit causal dynamics, causal reward, minimal abstraction",
    config=CBMConfig,
    trainer=lambda layout, cfg, seed: CBMTrainer(layout, cfg, seed=seed),
    model_from_config=model_from_config,
    global_graph=DynamicsCMI(),
    reward_graph=RewardCMI(),
    abstraction=minimal_abstraction,
    rollout_step=cbm_rollout_step,
    learns_reward=True,
)
