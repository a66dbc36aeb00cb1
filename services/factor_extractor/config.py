"""factor-extractor configuration."""
from __future__ import annotations

import math
from dataclasses import dataclass

from causal.slots import SlotConfig
from proto.settings import section
from services.runtime.config import ServiceConfig, doc

IDENTITIES = ("learned", "none")
MODES = ("slots", "latent-actions")


@dataclass(frozen=True)
class FactorExtractorConfig(ServiceConfig):
    """factor-extractor: learns Dyn-O's slots (eq. 7.1) from the env-workers' frames, freezes them, then
    publishes every FrameBatch as a TransitionBatch of slot factors; or, in a FLAM run, labels every
    FrameBatch with the learner's per-slot latent actions (``mode``)."""

    mode: str = doc("slots", "slots: learn Dyn-O's slots and publish the frames as slot transitions (a run with "
                             "--worker-publish-frames); latent-actions: label the frames with FLAM's per-slot latent "
                             "actions from the learner's weights, on latent/<worker> (a flam run with "
                             "--label-latent-actions); the slot settings below are for 'slots' only", choices=MODES)

    num_slots: int = doc(0, "K: slots per frame; 0 = objects + 1 (one per object of the env's spec and the background)")
    slot: SlotConfig = section(SlotConfig, prefix="slot", exclude=("num_slots",), slot_dim=16,
                               help="the slot representation (eq. 7.1); d_xi 16 keeps CDL's input over K slots small")
    ae_updates: int = doc(300, "phase 1: frame-autoencoder updates (then frozen)")
    ae_lr: float = doc(1e-3, "Adam learning rate of the frame autoencoder")
    slot_updates: int = doc(6000, "phase 2: slot updates, U of the mask-drop schedule; then the slots are frozen "
                                  "and transitions are published (at 1,500 the slots of 2 seeds in 6 had not bound "
                                  "yet: docs/results.md, 'How long the slots need')")
    replay_frames: int = doc(8192, "frames kept for learning the slots (oldest dropped)")
    warmup_frames: int = doc(256, "frames to hold before the first update")
    statistics_frames: int = doc(1024, "frames whose slots set the spec's per-slot loc and scale once frozen "
                                          "(at most identity_frames with the identity head)")
    identity: str = doc("learned", "which slot is which object once frozen: 'learned' (a head fitted on the training "
                                   "frames' masks puts each frame's slots in object order without masks, and the spec "
                                   "carries the object graph as truth; needs labelled frames and K = objects + 1) or "
                                   "'none' (slot attention's own order, free in each frame; no truth)")
    identity_frames: int = doc(4096, "frames the identity head is fitted on (the older four fifths) and scored on (the "
                                     "newest fifth): once the slots froze, frames go on filling the replay, unpublished, "
                                     "until it holds this many (at most replay_frames)")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.num_slots < 0 or min(self.ae_updates, self.slot_updates) < 0:
            raise ValueError("num_slots, ae_updates and slot_updates must be >= 0")
        if min(self.replay_frames, self.warmup_frames, self.statistics_frames) < 1:
            raise ValueError("replay_frames, warmup_frames and statistics_frames must be >= 1")
        if self.warmup_frames > self.replay_frames:
            raise ValueError(f"warmup_frames ({self.warmup_frames}) must be <= replay_frames ({self.replay_frames})")
        if self.identity not in IDENTITIES:
            raise ValueError(f"identity must be one of {IDENTITIES}, got {self.identity!r}")
        if self.identity_frames < 2:
            raise ValueError(f"identity_frames must be >= 2, got {self.identity_frames}")
        if not (math.isfinite(self.ae_lr) and self.ae_lr > 0):
            raise ValueError(f"ae_lr must be a positive finite number, got {self.ae_lr}")
