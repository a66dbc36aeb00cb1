"""dynamics-learner configuration."""
from __future__ import annotations

from dataclasses import dataclass

from causal.cdl import CDLConfig
from services.runtime.config import ServiceConfig, doc

_CDL = CDLConfig()


@dataclass(frozen=True)
class DynamicsLearnerConfig(ServiceConfig):
    """dynamics-learner: CDL on a bounded replay of the training episodes."""

    seed: int = doc(0, "seed of the model initialisation and of replay sampling")
    replay_capacity: int = doc(200_000, "transitions kept in the replay (oldest dropped)")
    warmup_steps: int = doc(2_000, "transitions to collect before the first update")
    heldout_fraction: float = doc(0.1, "fraction of episodes held out for CMI (not trained on)")
    feature_hidden: int = doc(_CDL.feature_hidden, "hidden width of each feature network")
    feature_dim: int = doc(_CDL.feature_dim, "feature size phi")
    predictor_hidden: int = doc(_CDL.predictor_hidden, "hidden width of each predictive head")
    lr: float = doc(_CDL.lr, "Adam learning rate")
    lr_decay_updates: int = doc(_CDL.lr_decay_updates, "cosine decay of the learning rate from lr to lr_final "
                                                       "over this many updates, constant after (0: no decay)")
    lr_final: float = doc(_CDL.lr_final, "learning rate at the end of the decay")
    batch_size: int = doc(_CDL.batch_size, "transitions per update")
    causal_every: int = doc(_CDL.causal_every, "causal likelihood term every N updates (eq. 3.3)")
    cmi_threshold: float = doc(_CDL.cmi_threshold, "CMI edge threshold epsilon_G, nats")
    publish_every_s: float = doc(3.0, "seconds between weight publications")
    checkpoint_every_s: float = doc(30.0, "seconds between checkpoints")
    max_updates: int = doc(0, "stop after this many updates (0: never)")
    updates_per_env_step: float = doc(0.0, "update only while updates < this x env steps ingested, so collectors "
                                           "of different speeds get the same training per step (0: as fast as possible)")

    def cdl(self) -> CDLConfig:
        return CDLConfig(feature_hidden=self.feature_hidden, feature_dim=self.feature_dim,
                         predictor_hidden=self.predictor_hidden, lr=self.lr,
                         lr_decay_updates=self.lr_decay_updates, lr_final=self.lr_final, batch_size=self.batch_size,
                         causal_every=self.causal_every, cmi_threshold=self.cmi_threshold)
