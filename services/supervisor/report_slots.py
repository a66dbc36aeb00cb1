"""The factor-extractor's blocks of summary.json: how good its frozen slots are (ch. 7,
``--worker-publish-frames``: ``slots``), or what its latent-action labels carry (ch. 8,
``--label-latent-actions``: ``latent_labels``, :func:`label_facts`).

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
from services.factor_extractor.latent import RECENT_BATCHES

SCORES = ("fg_ari", "identity_slot_accuracy", "identity_frame_accuracy", "published_identity_slot_accuracy",
          "published_identity_frame_accuracy")


def slot_facts(stats: ServiceStats | None) -> dict[str, Any]:
    """``{"slots": {...}}`` from a factor-extractor's beat once its slots are frozen ({} otherwise)."""
    if stats is None or not stats.values.get("ready") or "labelled_steps" in stats.values:
        return {}
    v = stats.values
    return {"slots": {"evaluation": "factor-extractor: frozen slots, no masks; held-out frames of its replay "
                                    "(published_*: every frame it published)",
                      **{k: float(v[k]) for k in SCORES if k in v},
                      **{k: int(v.get(k, 0)) for k in ("slot_updates", "frames_trained_on")},
                      **({"bound": bool(v["fg_ari"] >= BOUND_FG_ARI)} if "fg_ari" in v else {})}}


def label_facts(stats: ServiceStats | None) -> dict[str, Any]:
    """``{"latent_labels": {...}}`` from a labelling factor-extractor's last beat ({} for none, or for the
    slots mode): the steps it labelled and those that came before trained FLAM weights, the weights version
    it labelled with last, and each slot's mean KL to N(0, I) (nats per transition: what the labels of
    that slot carry on the workers' own stream) over its newest :data:`RECENT_BATCHES` batches
    (``slot_kl``) and over the run (``run_slot_kl``, every weights version since the first)."""
    if stats is None or "labelled_steps" not in stats.values:
        return {}
    v = stats.values

    def per_slot(prefix: str) -> list[float]:
        return [float(v[f"{prefix}{k}_kl"]) for k in range(len(v)) if f"{prefix}{k}_kl" in v]

    return {"latent_labels": {"evaluation": "factor-extractor: the env-workers' steps labelled with the newest FLAM "
                                            "weights' per-slot posteriors (clips s_t, s_t+1); slot_kl over its newest "
                                            f"{RECENT_BATCHES} batches, run_slot_kl over every labelled step",
                              **{k: int(v.get(k, 0)) for k in ("labelled_steps", "labelled_batches", "unlabelled_steps")},
                              "weights_version": int(v.get("labels_weights_version", 0)),
                              "slot_kl": per_slot("stream_slot"), "run_slot_kl": per_slot("run_slot")}}
