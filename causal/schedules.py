"""Learning-rate schedules shared by the learners (not in the dissertation; docs/deviations.md)."""
from __future__ import annotations

import math


def cosine_lr(lr: float, lr_final: float, updates: int, decay_updates: int) -> float:
    """The learning rate of update number ``updates`` (0-based): a cosine from ``lr`` down to
    ``lr_final`` over ``decay_updates`` updates, ``lr_final`` after; ``lr`` throughout when
    ``decay_updates`` <= 0."""
    if decay_updates <= 0:
        return lr
    progress = min(updates / decay_updates, 1.0)
    return lr_final + 0.5 * (lr - lr_final) * (1.0 + math.cos(math.pi * progress))
