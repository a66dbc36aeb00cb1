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
from causal.edge_tests import EdgeEstimate
from causal.method import Method
from causal.methods.cdl import CMIGraph
from causal.planning import cdl_rollout_step
from causal.rl import abstraction_input_mask

NO_IMPLICIT_NULL = "CBM's implicit dynamics have no permuted-input null: use --evaluator-bias fixed"


class DynamicsCMI:
    """Global graph: CMI of every (next factor, input) pair (eq. 4.3 implicit, eq. 3.2 explicit)."""

    name = "cmi"

    def __init__(self, seed: int = 0) -> None:
        self.generator = torch.Generator().manual_seed(seed)

    def permuted_null_refusal(self, cfg: CBMConfig) -> str | None:
        """Why a run of ``cfg`` cannot have the permuted-input null (implicit dynamics), or None."""
        return NO_IMPLICIT_NULL if cfg.dynamics == "implicit" else None

    def scores(self, model: CBMModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> np.ndarray:
        return model.dynamics_cmi(state, action, next_state, self.generator).numpy()

    def threshold(self, model: CBMModel) -> float:
        return model.cfg.cmi_threshold

    @torch.no_grad()
    def estimate(self, model: CBMModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                 permute: torch.Generator | None = None, max_samples: int | None = None) -> EdgeEstimate:
        """:meth:`scores` with standard errors over the transitions: eq. 4.3's per-sample terms on the
        same subsample (at most ``max_samples``, default ``cmi_samples``) and negatives (implicit; the
        negatives' own randomness is not in them), CDL's per-sample log-likelihood ratios on all of them
        (explicit, where ``permute`` also gives the permuted-input null; the implicit model has none:
        ValueError)."""
        if not model.implicit:
            return CMIGraph().estimate(model.dynamics, state, action, next_state, permute)
        if permute is not None:
            raise ValueError(NO_IMPLICIT_NULL)
        limit = max_samples or model.cfg.cmi_samples
        if state.shape[0] > limit:
            index = torch.randperm(state.shape[0], generator=self.generator)[:limit]
            state, action, next_state = state[index], action[index], next_state[index]
        total, squares = model.dynamics.cmi_sums(state, action, next_state, model.cfg.eval_negatives, self.generator)
        return EdgeEstimate.from_sums(total.numpy(), squares.numpy(), state.shape[0])


class RewardCMI:
    """Reward graph: CMI of the reward with every factor at t and the action (Assumption 7)."""

    name = "reward_cmi"

    def scores(self, model: CBMModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
               reward: torch.Tensor) -> np.ndarray:
        return model.reward_cmi(state, action, reward).numpy()

    def threshold(self, model: CBMModel) -> float:
        return model.cfg.reward_threshold

    def estimate(self, model: CBMModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                 reward: torch.Tensor) -> EdgeEstimate:
        """:meth:`scores` with delta-method standard errors (:meth:`CausalRewardModel.cmi_with_stderr`)."""
        cmi, stderr = model.reward.cmi_with_stderr(state, action, reward)
        return EdgeEstimate(cmi.double().numpy(), stderr.double().numpy(), state.shape[0])


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
