"""CBM's settings (dissertation ch. 4): one frozen dataclass, offered as ``--cbm-<field>`` flags."""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass

from causal.cdl import CDLConfig
from proto.settings import doc

DYNAMICS = ("implicit", "explicit")
TARGETS = ("delta", "next", "auto")


@dataclass(frozen=True)
class CBMConfig:
    """CBM (ch. 4): implicit (or explicit) masked dynamics, causal reward model, minimal task abstraction."""

    dynamics: str = doc("implicit", "dynamics model: implicit (InfoNCE energies, CMI by eq. 4.3) or explicit "
                                    "(CDL's Gaussian/categorical heads; the chapter's comparison)", choices=DYNAMICS)
    target: str = doc("next", "the dynamics' label for a continuous factor: its next value s^j_{t+1} (eq. "
                              "4.1's label), its change s^j_{t+1} - s^j_t (delta: the authors' code), or, implicit "
                              "only, per factor whichever varies less in the first batch (auto; the explicit model "
                              "takes changes then); see docs/methods/cbm.md", choices=TARGETS)
    feature_hidden: int = doc(32, "hidden width of each per-(output, input) feature network (as CDL's here)")
    feature_dim: int = doc(32, "size of every per-input feature vector")
    predictor_hidden: int = doc(64, "hidden width of each per-output head (dynamics and reward)")
    embed_dim: int = doc(32, "size of enc(s, a)_j and enc(delta s_j), whose inner product is the energy f_impl")
    candidate_hidden: int = doc(64, "hidden width of each continuous factor's candidate encoder enc(delta s_j)")
    reward_hidden: int = doc(128, "hidden width of the causal reward model's two layers (Fig. 4.2 (a))")
    num_negatives: int = doc(512, "negative candidates per factor per update, uniform over the delta range "
                                  "(the reference's 512)")
    eval_negatives: int = doc(8192, "negative candidates per factor for a CMI estimate (the reference's 8192)")
    cmi_samples: int = doc(256, "held-out transitions per implicit CMI estimate (a random subset of those the "
                                "evaluator passes; its moving average pools successive estimates)")
    score_l2: float = doc(1e-6, "lambda1 of eq. 4.5: L2 penalty on every candidate's score")
    grad_l2: float = doc(1e-6, "lambda2 of eq. 4.5: L2 penalty on the score's gradient w.r.t. the candidate")
    lr: float = doc(1e-3, "Adam learning rate (reference: 3e-4; see docs/deviations.md)")
    batch_size: int = doc(32, "transitions per update (the reference's 32)")
    causal_every: int = doc(10, "include the causal-parents term once every this many updates (as CDL)")
    grad_clip: float = doc(10.0, "gradient norm clip")
    cmi_threshold: float = doc(0.02, "dynamics edge threshold, nats: edge if CMI >= this")
    reward_threshold: float = doc(0.01, "reward edge threshold, nats: S^i is a parent of the reward if its "
                                         "reward CMI >= this")
    log_std_min: float = doc(-6.0, "explicit dynamics: lower clip of a continuous head's log standard deviation")
    log_std_max: float = doc(2.0, "explicit dynamics: upper clip of a continuous head's log standard deviation")

    def __post_init__(self) -> None:
        if self.dynamics not in DYNAMICS:
            raise ValueError(f"dynamics must be one of {DYNAMICS}, got {self.dynamics!r}")
        if self.target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {self.target!r}")
        for name in ("feature_hidden", "feature_dim", "predictor_hidden", "embed_dim", "candidate_hidden",
                     "reward_hidden", "num_negatives", "eval_negatives", "cmi_samples", "batch_size", "causal_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("lr", "grad_clip"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a positive finite number, got {getattr(self, name)}")
        for name in ("score_l2", "grad_l2", "cmi_threshold", "reward_threshold"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {getattr(self, name)}")
        if not self.log_std_min < self.log_std_max:
            raise ValueError(f"log_std_min ({self.log_std_min}) must be below log_std_max ({self.log_std_max})")

    def cdl(self) -> CDLConfig:
        """The explicit variant's settings: CDL's model with these widths, clips and threshold."""
        return CDLConfig(feature_hidden=self.feature_hidden, feature_dim=self.feature_dim,
                         predictor_hidden=self.predictor_hidden, lr=self.lr, batch_size=self.batch_size,
                         causal_every=self.causal_every, log_std_min=self.log_std_min,
                         log_std_max=self.log_std_max, grad_clip=self.grad_clip, cmi_threshold=self.cmi_threshold,
                         target="next" if self.target == "next" else "delta")

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)
