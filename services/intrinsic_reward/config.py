"""intrinsic-reward configuration."""
from __future__ import annotations

from dataclasses import dataclass

from causal.intrinsic import reward_names
from services.runtime.config import ServiceConfig, doc


@dataclass(frozen=True)
class IntrinsicRewardConfig(ServiceConfig):
    """intrinsic-reward: transitions in, ScoredBatches out, rewards from the method's weights and graph
    (or from this service's own ensemble)."""

    reward: str = doc("preddiff", "intrinsic reward (causal.intrinsic.REWARDS); a reward that reads the dynamics "
                                  "model must be one the run's method serves", choices=reward_names)
    eta: float = doc(1.0, "reward scale eta (inside tanh for preddiff, a plain factor for curiosity)")
    ensemble_members: int = doc(5, "disagreement: forward models K in the bootstrap ensemble")
    ensemble_hidden: int = doc(64, "disagreement: hidden width of each forward model")
    ensemble_lr: float = doc(1e-3, "disagreement: Adam learning rate")
    ensemble_updates_per_batch: int = doc(8, "disagreement: ensemble updates per scored batch (after scoring it)")
    ensemble_batch_size: int = doc(128, "disagreement: transitions per ensemble update")
    ensemble_warmup: int = doc(512, "disagreement: transitions before rewards are non-zero")
