"""graph-evaluator configuration."""
from __future__ import annotations

from dataclasses import dataclass

from causal.cdl import CDLConfig
from services.runtime.config import ServiceConfig, doc


@dataclass(frozen=True)
class GraphEvaluatorConfig(ServiceConfig):
    """graph-evaluator: CMI (eq. 3.2) on held-out transitions for every published weights version."""

    heldout_fraction: float = doc(0.1, "fraction of episodes held out (must match the learner)")
    heldout_capacity: int = doc(40_000, "held-out transitions kept (a ring buffer): each evaluation draws "
                                "eval_samples of them, so successive estimates see different episodes")
    min_heldout: int = doc(500, "held-out transitions needed before the first report")
    eval_samples: int = doc(2_000, "held-out transitions used per CMI evaluation")
    cmi_threshold: float = doc(CDLConfig().cmi_threshold, "CMI edge threshold epsilon_G, nats")
    cmi_ema: float = doc(0.999, "weight of the previous CMI estimate per learner update since it "
                         "(the reference's EMA): an evaluation k updates later keeps cmi_ema**k of it")
    min_interval_s: float = doc(2.0, "minimum seconds between evaluations")
    seed: int = doc(0, "seed of the held-out subsampling")
    checkpoint_every_s: float = doc(30.0, "seconds between checkpoints")

    def __post_init__(self) -> None:
        if not 0.0 <= self.cmi_ema < 1.0:
            raise ValueError(f"cmi_ema must be in [0, 1), got {self.cmi_ema}")
        if self.eval_samples <= 0 or self.heldout_capacity < self.min_heldout:
            raise ValueError("eval_samples must be positive and heldout_capacity >= min_heldout")
