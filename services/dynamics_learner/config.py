"""dynamics-learner configuration."""
from __future__ import annotations

from dataclasses import dataclass

from causal.methods import method_configs_class
from proto.settings import section
from services.runtime.config import ServiceConfig, doc

MethodConfigs = method_configs_class()


@dataclass(frozen=True)
class DynamicsLearnerConfig(ServiceConfig):
    """dynamics-learner: the run's method's dynamics model on a bounded replay of the training episodes."""

    replay_capacity: int = doc(200_000, "transitions kept in the replay (oldest dropped); raise it for runs "
                                        "longer than this many env steps")
    warmup_steps: int = doc(2_000, "transitions to collect before the first update")
    publish_every_s: float = doc(3.0, "seconds between weight publications")
    max_updates: int = doc(0, "stop after this many updates (0: never)")
    updates_per_env_step: float = doc(0.0, "update only while updates < this x env steps ingested, so collectors "
                                           "of different speeds get the same training per step (0: as fast as possible)")
    models: MethodConfigs = section(MethodConfigs, prefix="", help="every method's hyper-parameters")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.replay_capacity < 1 or self.warmup_steps < 0 or self.max_updates < 0:
            raise ValueError("replay_capacity must be >= 1, warmup_steps and max_updates >= 0")
        if not self.publish_every_s > 0 or not self.updates_per_env_step >= 0:
            raise ValueError("publish_every_s must be > 0 and updates_per_env_step >= 0")
