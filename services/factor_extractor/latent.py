"""factor-extractor core, second mode: FLAM's per-slot latent actions of the env-workers' frames. No bus.

In a FLAM run with ``--label-latent-actions true`` (chapter 8, issue 25 item 6) the env-workers publish
their steps twice: as transitions (the dynamics-learner trains FLAM on them) and as frames; the
extractor takes the learner's newest FLAM weights and labels every FrameBatch with each slot's latent
action posterior (eq. 8.4): a :class:`LatentActions` message per batch, one Gaussian per step and slot.

What a label is: the model's posterior for the clip of two frames (s_t, s_{t+1}) of that step, the
clip length the learner trains on (``causal.flam_learner``: the replay holds transitions, so FLAM is
trained on pairs), not a rollout over the whole episode. Steps are labelled only once the learner is
past its autoencoder phase (the weights' ``updates`` above the model's ``ae_updates``): before, the
latent-action networks are untrained and their labels would mean nothing; such batches are counted,
not published. Labels of a batch come from one weights version, which the message names.
"""
from __future__ import annotations

import json
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import torch

from causal.factored import FactorLayout
from causal.flam_learner import FLAMModel
from causal.flam_nets import gaussian_kl
from causal.method import import_tensors
from causal.methods import model_from_config_json
from causal.slots import FEATURE_STRIDE
from proto.codec import ProtocolError
from proto.messages import EnvSpec, FrameBatch, LatentActions, Weights
from services.factor_extractor.config import FactorExtractorConfig
from services.runtime.accept import VersionGate, check_weights_config
from services.runtime.checkpoint import check_fingerprint, load_checkpoint, save_checkpoint


RECENT_BATCHES = 64
"""Batches the recent per-slot KL is taken over (16,384 steps of 256-step batches): what the labels of
the current weights carry, where the run's mean mixes every version since the first."""


class LatentActionLabeller:
    """Labels FrameBatches with the per-slot latent actions of the newest FLAM weights taken."""

    def __init__(self, cfg: FactorExtractorConfig, env: EnvSpec) -> None:
        self.cfg, self.env = cfg, env
        self.layout = FactorLayout.from_spec(env)
        self.model: FLAMModel | None = None
        self.model_config = ""
        self.weights_version, self.weights_updates = 0, 0
        self.versions = VersionGate(known=cfg.known_version)
        self.labelled_steps, self.labelled_batches, self.unlabelled_steps = 0, 0, 0
        self.kl_sum: np.ndarray | None = None
        """Each slot's KL to N(0, I) summed over every labelled step (nats)."""
        self.recent: deque[tuple[int, np.ndarray]] = deque(maxlen=RECENT_BATCHES)
        """(steps, per-slot KL sum) of the newest labelled batches."""

    @property
    def ready(self) -> bool:
        """FLAM weights past the autoencoder phase are held: steps can be labelled."""
        return self.model is not None and self.weights_updates > self.model.config.ae_updates

    def load_weights(self, weights: Weights) -> bool:
        """Use newer weights. ValueError, before any model is built, for weights of another method or
        factor layout, or whose configuration does not describe their tensors; ProtocolError for a
        version that jumps past the bound (:mod:`services.runtime.accept`)."""
        if weights.version <= self.weights_version or not self.versions.newer("weights", weights.version):
            return False
        if weights.config_json != self.model_config:
            check_weights_config(weights.config_json, weights.tensors, self.cfg.method, self.layout,
                                 model_from_config_json)
            model = model_from_config_json(weights.config_json)
            if not isinstance(model, FLAMModel):
                raise ValueError(f"weights of a {type(model).__name__}: latent actions need FLAM's")
            self.model, self.model_config = model.eval(), weights.config_json
        import_tensors(self.model, weights.tensors)
        self.versions.accept("weights", weights.version)
        self.weights_version, self.weights_updates = weights.version, weights.updates
        return True

    def label(self, batch: FrameBatch) -> LatentActions | None:
        """The batch's per-slot latent actions, or None while no trained FLAM weights are held (the
        steps are counted as unlabelled). ProtocolError for frames the model cannot read."""
        if not self.ready:
            self.unlabelled_steps += len(batch)
            return None
        size = self.model.grid_size * FEATURE_STRIDE
        if batch.frames.shape[1:3] != (size, size):
            raise ProtocolError("inconsistent", f"FrameBatch: frames {batch.frames.shape[1:3]}, the FLAM model reads "
                                                f"{size}x{size} ({self.model.grid_size} cells of {FEATURE_STRIDE} "
                                                "pixels)")
        mean, log_sigma = self.posterior(batch.frames, batch.state_frame, batch.next_frame)
        kl = gaussian_kl(mean, log_sigma).sum(0).double().numpy()
        self.kl_sum = kl if self.kl_sum is None else self.kl_sum + kl
        self.recent.append((len(batch), kl))
        self.labelled_steps += len(batch)
        self.labelled_batches += 1
        return LatentActions(kind=self.cfg.method, worker_id=batch.worker_id, seq=batch.seq,
                             weights_version=self.weights_version, episode_id=batch.episode_id, step=batch.step,
                             mean=mean.numpy().astype(np.float32), log_sigma=log_sigma.numpy().astype(np.float32))

    @torch.no_grad()
    def posterior(self, frames: np.ndarray, state_frame: np.ndarray,
                  next_frame: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Means and log standard deviations ``[T, K, d_a]`` of each step's clip (s_t, s_{t+1}): each distinct
        frame is encoded once, then the steps' pairs go through the factorizer and the IDM together."""
        features = self.model.features(torch.from_numpy(frames)[None])[0]
        clips = torch.stack([features[torch.from_numpy(state_frame).long()],
                             features[torch.from_numpy(next_frame).long()]], dim=1)
        mean, log_sigma = self.model.lam.posterior(clips)
        return mean[:, 0], log_sigma[:, 0]

    def slot_kl(self) -> list[float]:
        """Each slot's mean KL to N(0, I) over the newest :data:`RECENT_BATCHES` labelled batches (nats per
        transition: what its labels carry under the current weights)."""
        if not self.recent:
            return []
        return [float(v) for v in sum(kl for _, kl in self.recent) / sum(n for n, _ in self.recent)]

    def run_slot_kl(self) -> list[float]:
        """Each slot's mean KL over every step labelled in the run, whatever the weights version."""
        if self.kl_sum is None or not self.labelled_steps:
            return []
        return [float(v) for v in self.kl_sum / self.labelled_steps]

    def progress(self) -> dict[str, float]:
        return {"ready": float(self.ready), "labels_weights_version": self.weights_version,
                "labelled_steps": self.labelled_steps, "labelled_batches": self.labelled_batches,
                "unlabelled_steps": self.unlabelled_steps, "env_steps": self.labelled_steps + self.unlabelled_steps,
                **{f"stream_slot{k}_kl": v for k, v in enumerate(self.slot_kl())},
                **{f"run_slot{k}_kl": v for k, v in enumerate(self.run_slot_kl())}}

    def fingerprint(self) -> str:
        return json.dumps({"mode": "latent-actions", "env": self.env.env_id, "method": self.cfg.method,
                           "env_config": json.loads(self.env.config_json)}, sort_keys=True)

    def checkpoint(self, path: Path) -> None:
        """The counts and KL sums (the run's figures cover the whole run across a restart; the recent window
        starts afresh) and the last
        weights version taken (its first version after a restart is bounded by it); no model: a restarted
        labeller takes the learner's newest weights from the bus."""
        save_checkpoint({"fingerprint": self.fingerprint(), "labelled_steps": self.labelled_steps,
                         "labelled_batches": self.labelled_batches, "unlabelled_steps": self.unlabelled_steps,
                         "kl_sum": [] if self.kl_sum is None else [float(v) for v in self.kl_sum],
                         "weights_version": self.weights_version}, path)

    def restore(self, path: Path) -> bool:
        saved: dict[str, Any] | None = load_checkpoint(path)
        if saved is None:
            return False
        check_fingerprint(saved, self.fingerprint(), path)
        self.labelled_steps, self.labelled_batches = int(saved["labelled_steps"]), int(saved["labelled_batches"])
        self.unlabelled_steps = int(saved["unlabelled_steps"])
        self.kl_sum = np.asarray(saved["kl_sum"], np.float64) if saved["kl_sum"] else None
        self.versions.know(int(saved["weights_version"]))
        return True
