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
    resumable=("lr_decay_updates", "lr_final"),
    devices=("cpu", "cuda"),
)
