"""graph-evaluator configuration."""
from __future__ import annotations

from dataclasses import dataclass

from causal.cdl import CDLConfig
from services.runtime.config import ServiceConfig, doc


@dataclass(frozen=True)
class GraphEvaluatorConfig(ServiceConfig):
    """graph-evaluator: CMI (eq. 3.2) on held-out transitions for every published weights version."""

    heldout_fraction: float = doc(0.1, "fraction of episodes held out (must match the learner)")
    heldout_capacity: int = doc(4_000, "held-out transitions kept (a ring buffer)")
    min_heldout: int = doc(500, "held-out transitions needed before the first report")
    eval_samples: int = doc(2_000, "held-out transitions used per CMI evaluation")
    cmi_threshold: float = doc(CDLConfig().cmi_threshold, "CMI edge threshold epsilon_G, nats")
    cmi_ema: float = doc(0.5, "weight of the previous estimate in the CMI moving average")
    min_interval_s: float = doc(2.0, "minimum seconds between evaluations")
    seed: int = doc(0, "seed of the held-out subsampling")
    checkpoint_every_s: float = doc(30.0, "seconds between checkpoints")
