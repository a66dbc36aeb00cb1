"""ELDEN (dissertation ch. 5) as a Causeway method: the attention ensemble, its local dependency
graphs from partial derivatives (eq. 5.1), their variance across members as an intrinsic reward
(Algorithm 6), and prediction-error prioritised replay (optional).

ELDEN has no global graph (``global_graph=None``): chapter 5 defines only local graphs, and a
summary of them (say, the mean derivative over held-out transitions) would be a new estimator
with a scale and threshold of its own; it would also hand the policy-learner an abstraction
mask, which ELDEN's exploration does not use. The parts live in :mod:`causal.elden` (model),
:mod:`causal.elden_graphs` (local graphs, attention baseline, reward) and
:mod:`causal.elden_trainer` (eqs. 5.2-5.3, Mixup, priorities).
"""
from __future__ import annotations

import numpy as np
import torch

from causal.elden import ELDENConfig, ELDENModel, model_from_config
from causal.elden_graphs import attention_graphs, local_graphs
from causal.elden_masks import MaskedELDENModel, mask_graphs
from causal.elden_trainer import ELDENTrainer
from causal.method import Method


class JacobianLocalGraph:
    """Local graphs (eq. 5.1): ``|d p(s^j_{t+1}) / d s^i_t|`` averaged over the members; edge at ``edge_threshold``."""

    name = "jacobian"

    def scores(self, model: ELDENModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> np.ndarray:
        return local_graphs(model, state, action, next_state).numpy()

    def threshold(self, model: ELDENModel) -> float:
        return model.cfg.edge_threshold


class AttentionLocalGraph:
    """The "Attn" baseline of Table 5.1 on ELDEN's network: attention from input ``i`` through the
    self-attention layers to output ``j``, averaged over heads and members. Its threshold is uniform
    attention, ``1 / (d_S + 1)`` (the chapter gives none; Table 5.1 searches the best one)."""

    name = "attention"

    def scores(self, model: ELDENModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> np.ndarray:
        return attention_graphs(model, state, action).numpy()

    def threshold(self, model: ELDENModel) -> float:
        return 1.0 / model.num_inputs


LOCAL_ESTIMATORS = {"jacobian": JacobianLocalGraph(), "attention": AttentionLocalGraph()}
"""Every local-graph estimator an ELDEN model supports (the benchmark of Table 5.1 runs them all)."""


class MaskLocalGraph:
    """Table 5.1's "Input Mask" or "Attn Mask" baseline: the learned mask of a
    :class:`~causal.elden_masks.MaskedELDENModel` (its own model, trained by :class:`~causal.elden_masks.MaskTrainer`),
    averaged over members; an edge where the mask is open with probability at least 0.5."""

    def __init__(self, kind: str) -> None:
        self.kind, self.name = kind, f"{kind}-mask"

    def scores(self, model: MaskedELDENModel, state: torch.Tensor, action: torch.Tensor,
               next_state: torch.Tensor) -> np.ndarray:
        if getattr(model, "mask_cfg", None) is None or model.mask_cfg.kind != self.kind:
            raise ValueError(f"the {self.name} estimator reads a MaskedELDENModel of kind {self.kind!r}")
        return mask_graphs(model, state, action).numpy()

    def threshold(self, model: MaskedELDENModel) -> float:
        return 0.5


MASK_ESTIMATORS = {"input-mask": MaskLocalGraph("input"), "attention-mask": MaskLocalGraph("attention")}
"""The learned-mask baselines of Table 5.1 (ch. 5.3.1), each on a model of its own: not in
:data:`LOCAL_ESTIMATORS`, whose estimators read the ELDEN model a run trains (see docs/methods/elden.md)."""

METHOD = Method(
    name="elden",
    title="ELDEN (ch. 5): attention ensemble, local graphs from partial derivatives, graph-variance exploration",
    config=ELDENConfig,
    trainer=lambda layout, cfg, seed: ELDENTrainer(layout, cfg, seed=seed),
    model_from_config=model_from_config,
    global_graph=None,
    local_graph=LOCAL_ESTIMATORS["jacobian"],
    intrinsic=("elden", "curiosity"),
    prioritised=True,
)
