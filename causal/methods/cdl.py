"""CDL (dissertation ch. 3) as a Causeway method: the masked factored dynamics model, the global graph
from CMI (eq. 3.2), point-wise CMI as its local graphs, and the task-independent abstraction.

The parts live in :mod:`causal.cdl` (model), :mod:`causal.cdl_trainer` (eq. 3.3),
:mod:`causal.abstraction` and :mod:`causal.planning`; this module only names them for the registry.
"""
from __future__ import annotations

import numpy as np
import torch

from causal.abstraction import cdl_abstraction
from causal.cdl import CDLConfig, CDLModel, model_from_config
from causal.cdl_trainer import CDLTrainer
from causal.edge_tests import EdgeEstimate
from causal.method import Method
from causal.planning import cdl_rollout_step


class CMIGraph:
    """Global graph: CMI of every (output, input) pair on held-out transitions (eq. 3.2), inputs
    that are constant over the sample set to 0 (see :meth:`CDLModel.cmi`)."""

    name = "cmi"

    def scores(self, model: CDLModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> np.ndarray:
        return model.cmi(state, action, next_state).cpu().numpy()

    def threshold(self, model: CDLModel) -> float:
        return model.cfg.cmi_threshold

    @torch.no_grad()
    def estimate(self, model: CDLModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                 permute: torch.Generator | None = None, chunk: int = 4096) -> EdgeEstimate:
        """The same CMI with standard errors from its per-sample log-likelihood ratios (the point-wise
        CMI), streamed in chunks; constant inputs are 0 with standard error 0, as in :meth:`scores`.
        With ``permute``, also the permuted-input null of :mod:`causal.edge_tests` (each input read
        from the sample a permutation of the whole set, drawn from ``permute``, assigns)."""
        sums = [np.zeros((model.num_outputs, model.num_inputs)) for _ in range(4 if permute is not None else 2)]
        n = state.shape[0]
        order = None if permute is None else torch.randperm(n, generator=permute).to(state.device)
        for start in range(0, n, chunk):
            part = slice(start, start + chunk)
            terms = [model.pointwise_cmi(state[part], action[part], next_state[part])]
            if order is not None:
                terms.append(permuted_terms(model, state[part], action[part], next_state[part],
                                            state[order[part]], action[order[part]]))
            for k, term in enumerate(terms):
                term = term.double().cpu()
                sums[2 * k] += term.sum(dim=0).numpy()
                sums[2 * k + 1] += term.square().sum(dim=0).numpy()
        estimate = EdgeEstimate.from_sums(sums[0], sums[1], n, *sums[2:])
        if n:
            constant = model.constant_inputs(state, action).cpu().numpy()
            for values in (estimate.cmi, estimate.stderr, estimate.null, estimate.excess_stderr):
                if values is not None:
                    values[:, constant] = 0.0
        return estimate


@torch.no_grad()
def permuted_terms(model: CDLModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                   other_state: torch.Tensor, other_action: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """Per-sample ``CMI - null`` terms (:meth:`CDLModel.permuted_gain`), ``[B, J, I]`` graph order."""
    out = torch.empty(state.shape[0], model.num_outputs, model.num_inputs, device=state.device)
    for start in range(0, state.shape[0], chunk):
        parts = (t[start : start + chunk] for t in (state, action, next_state, other_state, other_action))
        out[start : start + chunk] = model.to_graph_order(model.permuted_gain(*parts).permute(2, 0, 1))
    return out


class PointwiseCMI:
    """Local graphs: point-wise CMI of each transition (the pCMI of chapters 5-6), same threshold."""

    name = "pcmi"

    def scores(self, model: CDLModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> np.ndarray:
        return model.pointwise_cmi(state, action, next_state).cpu().numpy()

    def threshold(self, model: CDLModel) -> float:
        return model.cfg.cmi_threshold


METHOD = Method(
    name="cdl",
    title="Causal Dynamics Learning (ch. 3): masked dynamics, CMI graph, task-independent abstraction",
    config=CDLConfig,
    trainer=lambda layout, cfg, seed: CDLTrainer(layout, cfg, seed=seed),
    model_from_config=model_from_config,
    global_graph=CMIGraph(),
    local_graph=PointwiseCMI(),
    abstraction=cdl_abstraction,
    intrinsic=("preddiff", "curiosity"),
    rollout_step=cdl_rollout_step,
    resumable=("lr_decay_updates", "lr_final", "train_precision"),
    devices=("cpu", "cuda"),
)
