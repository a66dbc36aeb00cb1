"""The learner's live scores (``live_*`` values of its beats) as a history: the supervisor's
``live_history`` in a run's summary and the live page's latent-action curves."""
from __future__ import annotations

from typing import Mapping


def live_row(values: Mapping[str, float], last: Mapping[str, float] | None, elapsed: float) -> dict[str, float] | None:
    """A row of the learner's live-score history from one of its beats: the ``live_*`` values (a
    trainer's scores on fixed unseen data, e.g. FLAM's PSNR, DCI and per-slot KL; the prefix dropped)
    with the beat's ``time``, ``updates`` and ``env_steps``; None when the beat carries none or the same
    ones as ``last`` (a beat repeats the newest scores until the trainer computes the next)."""
    live = {key.removeprefix("live_"): float(v) for key, v in values.items() if key.startswith("live_")}
    if not live or (last is not None and all(last.get(key) == v for key, v in live.items())):
        return None
    return {"time": round(elapsed, 3), "updates": float(values.get("updates", 0.0)),
            "env_steps": float(values.get("env_steps", 0.0)), **live}
