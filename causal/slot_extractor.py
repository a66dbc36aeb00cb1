"""Dyn-O's slot representation (eq. 7.1) learned from a stream of frames, then frozen: what the
factor-extractor service runs (``services/factor_extractor``).

The phases are Algorithm 8's first two, in the order the Dyn-O learner runs them
(:class:`causal.dyno.DynOTrainer`), on frames that arrive instead of frames drawn from replayed states:

1. ``ae_updates``: the frame autoencoder (Enc/Dec) by reconstruction, then frozen;
2. ``slot_updates``: slot attention and the slot decoder on eq. 7.1 with the mask prior of
   ``config.mask_prior`` (annealed: masks dropped with probability log(1 + u) / log(1 + U));
3. frozen: :meth:`FrameSlotLearner.encode` gives each frame's slots, without masks.

The representation never changes once frozen, so every transition the extractor publishes is in the
same factor space (a dynamics model learned over slots that kept moving would chase its inputs).
"""
from __future__ import annotations

import copy
from typing import Any

import torch
import torch.nn.functional as F

from causal.slots import SlotConfig, SlotModel, SlotTrainer, frames_to_tensor

PHASES = ("autoencoder", "slots", "frozen")


class FrameSlotLearner:
    """A :class:`~causal.slots.SlotModel` trained phase by phase on batches of frames, then frozen."""

    def __init__(self, config: SlotConfig, frame_size: int, ae_updates: int, slot_updates: int, ae_lr: float,
                 seed: int) -> None:
        torch.manual_seed(seed)
        self.config, self.frame_size = config, frame_size
        self.ae_updates, self.slot_updates = ae_updates, slot_updates
        self.model = SlotModel(config, frame_size)
        self.ae_optimizer = torch.optim.Adam(self.model.autoencoder.parameters(), lr=ae_lr)
        self.slot_trainer = SlotTrainer(self.model, slot_updates, seed=seed)
        self.updates = 0
        self._freeze_done_parts()

    @property
    def phase(self) -> str:
        if self.updates < self.ae_updates:
            return "autoencoder"
        return "slots" if self.updates < self.ae_updates + self.slot_updates else "frozen"

    @property
    def frozen(self) -> bool:
        return self.phase == "frozen"

    def update(self, frames: torch.Tensor, labels: torch.Tensor | None) -> dict[str, float]:
        """One update of the current phase on frames uint8 ``[B, H, W, 3]`` and their label maps ``[B, H, W]``
        (None: no masks, only with ``mask_prior="none"``); its losses. ``RuntimeError`` once frozen."""
        phase = self.phase
        if phase == "frozen":
            raise RuntimeError("the slot representation is frozen: no more updates")
        if phase == "autoencoder":
            images = frames_to_tensor(frames)
            loss = F.mse_loss(self.model.autoencoder(images), images)
            self.ae_optimizer.zero_grad()
            loss.backward()
            self.ae_optimizer.step()
            stats = {"autoencoder_mse": float(loss.detach())}
        else:
            if labels is None and self.config.mask_prior != "none":
                raise ValueError(f"mask prior {self.config.mask_prior!r} needs the frames' labels")
            stats = self.slot_trainer.update(frames, labels if labels is not None else torch.zeros(frames.shape[:3]))
        self.updates += 1
        self._freeze_done_parts()
        return {**stats, "phase": float(PHASES.index(phase))}

    def _freeze_done_parts(self) -> None:
        self.model.autoencoder.requires_grad_(self.updates < self.ae_updates)
        if self.frozen:
            self.model.requires_grad_(False)
            self.model.eval()

    @torch.no_grad()
    def encode(self, frames: torch.Tensor, chunk: int = 256) -> torch.Tensor:
        """Slots ``[B, K, d_xi]`` of frames uint8 ``[B, H, W, 3]``, no masks (inference as in Table 7.1)."""
        if not len(frames):
            return torch.empty(0, self.config.num_slots, self.config.slot_dim)
        return self.encode_with_masks(frames, chunk)[0]

    @torch.no_grad()
    def encode_with_masks(self, frames: torch.Tensor, chunk: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
        """Slots ``[B, K, d_xi]`` and their decoder masks (alpha, ``[B, K, n]`` over feature tokens), no masks given."""
        self.model.eval()
        outs = [self.model(frames[i : i + chunk]) for i in range(0, len(frames), chunk)]
        return torch.cat([o.slots for o in outs]), torch.cat([o.alpha for o in outs])

    @torch.no_grad()
    def segment(self, frames: torch.Tensor) -> torch.Tensor:
        """Each pixel's slot (int ``[B, H, W]``), no masks: what FG-ARI scores."""
        self.model.eval()
        return self.model.segment(frames)

    def state_dict(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "updates": self.updates,
                "ae_optimizer": self.ae_optimizer.state_dict(), "slot_optimizer": self.slot_trainer.optimizer.state_dict(),
                "slot_updates": self.slot_trainer.updates, "mask_generator": self.slot_trainer.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        state = copy.deepcopy(state)
        self.model.load_state_dict(state["model"])
        self.ae_optimizer.load_state_dict(state["ae_optimizer"])
        self.slot_trainer.optimizer.load_state_dict(state["slot_optimizer"])
        self.updates, self.slot_trainer.updates = int(state["updates"]), int(state["slot_updates"])
        self.slot_trainer.generator.set_state(state["mask_generator"])
        self._freeze_done_parts()
