"""The factor-extractor's block of summary.json (ch. 7, ``--worker-publish-frames``): how good its frozen slots are.

From the extractor's last beat, under the contract's ``slots`` key: ``fg_ari`` (the slots' segmentation
of held-out frames of its replay, no masks), ``identity_slot_accuracy`` / ``identity_frame_accuracy``
(how often the identity head gave a slot the object its mask holds, per slot and with every slot of a
frame right, on the same frames), ``published_identity_*`` (the same over every frame it published),
the slot budget (``slot_updates``, ``frames_trained_on``), and ``bound``: whether the held-out FG-ARI
reached :data:`causal.fg_ari.BOUND_FG_ARI` (false: the slots froze before slot attention bound the
objects, and the run's graph is over image parts).
"""
from __future__ import annotations

from typing import Any

from causal.fg_ari import BOUND_FG_ARI
from proto.messages import ServiceStats

SCORES = ("fg_ari", "identity_slot_accuracy", "identity_frame_accuracy", "published_identity_slot_accuracy",
          "published_identity_frame_accuracy")


def slot_facts(stats: ServiceStats | None) -> dict[str, Any]:
    """``{"slots": {...}}`` from a factor-extractor's beat once its slots are frozen ({} otherwise)."""
    if stats is None or not stats.values.get("ready"):
        return {}
    v = stats.values
    return {"slots": {"evaluation": "factor-extractor: frozen slots, no masks; held-out frames of its replay "
                                    "(published_*: every frame it published)",
                      **{k: float(v[k]) for k in SCORES if k in v},
                      **{k: int(v.get(k, 0)) for k in ("slot_updates", "frames_trained_on")},
                      **({"bound": bool(v["fg_ari"] >= BOUND_FG_ARI)} if "fg_ari" in v else {})}}
