"""Dyn-O as one trainable model (chapter 7): the slot representation (eq. 7.1, :mod:`causal.slots`)
and the slot world model (eq. 7.2, :mod:`causal.slot_world_model`), trained in the dynamics-learner on
the run's transitions.

The bus carries no frames yet (the factor-extractor service of issue 24 is not built), so the trainer
draws its frames itself: each transition's state and next state are rendered with ``chemical-pixels``'
renderer (:class:`envs.chemical_pixels.ChemicalPixelsEnv.render_states`), which is how that env draws
its own frames, with the renderer's exact masks as the mask prior. Phases by update count, as
Algorithm 8 orders them:

1. ``ae_updates``: the frame autoencoder (Enc/Dec) by reconstruction, then frozen;
2. ``slot_updates``: slot attention and the slot decoder on eq. 7.1, the masks dropped with
   probability log(1 + u) / log(1 + U) (U = ``slot_updates``);
3. then: the world model on eq. 7.2, one step per transition (the replay holds transitions, not
   sequences), against the next frame's slots matched to the predictions (slot order is free in each
   frame and Chemical redraws positions every step): :func:`matched_slot_mse`.

:class:`SlotScores` is the method's ``slots`` role: the final model's FG-ARI on frames of unseen states,
without masks, which a run's ``summary.json`` carries as ``slots.fg_ari``.
"""
from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from torch import nn

from causal.factored import FactorLayout
from causal.fg_ari import mean_fg_ari
from causal.method import layout_from_config, model_config_json
from causal.slot_world_model import SlotWorldModel, WorldModelConfig
from causal.slots import MASK_PRIORS, TOKEN_MASKS, SlotConfig, SlotModel, SlotTrainer, frames_to_tensor
from envs.chemical_pixels import ChemicalPixelsEnv
from proto.messages import EnvSpec
from proto.settings import doc

SCORE_SEED = 10_000
"""The FG-ARI frames come from a renderer seeded with this: states no run draws from its own seed."""


@dataclass(frozen=True)
class DynOConfig:
    """Dyn-O (ch. 7): the frames the learner renders, the slot representation, the world model, the phases."""

    frame_size: int = doc(32, "side of the frames the learner renders from each transition's states (pixels)")
    num_slots: int = doc(0, "K: slots per frame; 0 = objects + 1 (one per object and the background)")
    slot_dim: int = doc(32, "d_xi: size of one slot")
    feature_dim: int = doc(16, "d_e: channels of the frame autoencoder's feature tokens")
    iterations: int = doc(3, "slot-attention refinement steps")
    mask_prior: str = doc("annealed", "annealed (Dyn-O), none (SOLV) or always (the oracle)", choices=MASK_PRIORS)
    token_mask: str = doc("touch", "which slots a feature token may take under the masks: touch (any object it "
                                   "touches and the background) or objects (only the objects it touches)",
                          choices=TOKEN_MASKS)
    mask_binding: float = doc(0.0, "weight of the mask prior's binding term (causal.slots.SlotConfig.mask_binding; "
                                   "not in the chapter; with token_mask objects it is what lifts the annealed "
                                   "prior above no prior on objects of two parts, docs/results.md)")
    two_tone: bool = doc(False, "render each shape's lower half in one grey shared by all objects (objects of "
                                "two parts: envs.chemical_pixels.ChemicalPixelsEnv.two_tone); --env "
                                "chemical-pixels-two-tone sets it")
    ae_updates: int = doc(300, "phase 1: frame-autoencoder updates (then frozen)")
    slot_updates: int = doc(1500, "phase 2: slot updates, U of the mask-drop schedule")
    ae_lr: float = doc(1e-3, "Adam learning rate of the frame autoencoder")
    slot_lr: float = doc(3e-3, "Adam learning rate of slot attention and the slot decoder")
    wm_hidden: int = doc(64, "per-slot hidden state of the world model's recurrent core")
    wm_lr: float = doc(1e-3, "Adam learning rate of the world model (phase 3)")
    batch_size: int = doc(32, "transitions per update (each gives two frames)")

    def __post_init__(self) -> None:
        counts = (self.frame_size, self.slot_dim, self.feature_dim, self.iterations, self.wm_hidden, self.batch_size)
        if min(counts) < 1 or min(self.num_slots, self.ae_updates, self.slot_updates) < 0:
            raise ValueError("Dyn-O sizes and the batch must be positive, num_slots and phase lengths not negative")
        if not all(math.isfinite(x) and x > 0 for x in (self.ae_lr, self.slot_lr, self.wm_lr)):
            raise ValueError("Dyn-O learning rates must be positive finite numbers")
        if self.mask_prior not in MASK_PRIORS:
            raise ValueError(f"mask_prior must be one of {MASK_PRIORS}, got {self.mask_prior!r}")
        if self.token_mask not in TOKEN_MASKS:
            raise ValueError(f"token_mask must be one of {TOKEN_MASKS}, got {self.token_mask!r}")
        if not (math.isfinite(self.mask_binding) and self.mask_binding >= 0):
            raise ValueError(f"mask_binding must be a finite number >= 0, got {self.mask_binding}")

    def slots(self, num_objects: int) -> SlotConfig:
        return SlotConfig(num_slots=self.num_slots or num_objects + 1, feature_dim=self.feature_dim,
                          slot_dim=self.slot_dim, iterations=self.iterations, lr=self.slot_lr,
                          batch_size=self.batch_size, mask_prior=self.mask_prior, token_mask=self.token_mask,
                          mask_binding=self.mask_binding)


def chemical_geometry(layout: FactorLayout) -> tuple[int, int]:
    """Objects and colours of a Chemical layout (``obj{k}.color``, ``obj{k}.x``, ``obj{k}.y`` per object);
    ``ValueError`` for any other, which Dyn-O cannot render."""
    n = layout.num_factors // 3
    expected = tuple(f"obj{k}.{f}" for k in range(n) for f in ("color", "x", "y"))
    if n < 1 or tuple(layout.names) != expected:
        raise ValueError("Dyn-O renders Chemical states only (factors obj<k>.color, obj<k>.x, obj<k>.y)")
    return n, int(layout.sizes[0])


class DynOModel(nn.Module):
    """The slot model (eq. 7.1) and the slot world model (eq. 7.2) of one Chemical layout."""

    def __init__(self, layout: FactorLayout, config: DynOConfig) -> None:
        super().__init__()
        self.layout, self.config = layout, config
        self.num_objects, self.num_colors = chemical_geometry(layout)
        self.slots = SlotModel(config.slots(self.num_objects), config.frame_size)
        self.world = SlotWorldModel(config.slot_dim, self.num_objects * self.num_colors,
                                    WorldModelConfig(hidden=config.wm_hidden))

    def renderer(self) -> ChemicalPixelsEnv:
        return ChemicalPixelsEnv(graph="chain", num_objects=self.num_objects, num_colors=self.num_colors,
                                 frame_size=self.config.frame_size, two_tone=self.config.two_tone)


def model_from_config(data: dict[str, Any]) -> DynOModel:
    return DynOModel(layout_from_config(data), DynOConfig(**data["dyno"]))


def matched_slot_mse(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error of slots ``[B, K, d]`` against ``target`` reordered, per sample, by the
    assignment of least total error (the loss is blind to the free order of slot attention's slots)."""
    cost = torch.cdist(predicted.detach(), target).square().numpy()
    order = torch.as_tensor(np.stack([linear_sum_assignment(c)[1] for c in cost]))
    return F.mse_loss(predicted, target.gather(1, order[..., None].expand_as(target)))


class DynOTrainer:
    """Dyn-O's three phases with the dynamics-learner's trainer interface (``update(s, a, s')``)."""

    def __init__(self, layout: FactorLayout, config: DynOConfig, seed: int) -> None:
        torch.manual_seed(seed)
        self.config, self.batch_size = config, config.batch_size
        self.model = DynOModel(layout, config)
        self.render = self.model.renderer()
        self.ae_optimizer = torch.optim.Adam(self.model.slots.autoencoder.parameters(), lr=config.ae_lr)
        self.slot_trainer = SlotTrainer(self.model.slots, config.slot_updates, seed=seed)
        self.wm_optimizer = torch.optim.Adam(self.model.world.parameters(), lr=config.wm_lr)
        self.updates = 0

    @property
    def phase(self) -> str:
        if self.updates < self.config.ae_updates:
            return "autoencoder"
        return "slots" if self.updates < self.config.ae_updates + self.config.slot_updates else "world_model"

    @property
    def lr(self) -> float:
        return {"autoencoder": self.config.ae_lr, "slots": self.config.slot_lr, "world_model": self.config.wm_lr}[self.phase]

    def frames(self, states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames (uint8 ``[B, H, W, 3]``) and label maps of states ``[B, 3N]``, drawn by the renderer."""
        frames, labels = self.render.render_states(states.detach().cpu().numpy())
        return torch.from_numpy(frames), torch.from_numpy(labels.astype(np.int64))

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        """One update of the current phase; returns its losses and the phase (0, 1, 2)."""
        phase = self.phase
        if phase == "autoencoder":
            stats = self._autoencoder_step(torch.cat([state, next_state]))
        elif phase == "slots":
            stats = self.slot_trainer.update(*self.frames(torch.cat([state, next_state])))
            if self.slot_trainer.updates == self.config.slot_updates:
                self.model.slots.requires_grad_(False)
        else:
            stats = self._world_model_step(state, action, next_state)
        self.updates += 1
        return {**stats, "phase": float(("autoencoder", "slots", "world_model").index(phase))}

    def _autoencoder_step(self, states: torch.Tensor) -> dict[str, float]:
        images = frames_to_tensor(self.frames(states)[0])
        autoencoder = self.model.slots.autoencoder
        loss = F.mse_loss(autoencoder(images), images)
        self.ae_optimizer.zero_grad()
        loss.backward()
        self.ae_optimizer.step()
        if self.updates + 1 == self.config.ae_updates:
            autoencoder.requires_grad_(False)
        return {"autoencoder_mse": float(loss.detach())}

    def _world_model_step(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        self.model.slots.eval()
        with torch.no_grad():
            slots = self.model.slots(self.frames(torch.cat([state, next_state]))[0]).slots
        now, target = slots.chunk(2)
        world = self.model.world
        step = world.step(now, action.view(-1).long(), world.initial_hidden(now))
        loss = matched_slot_mse(step.next_slots, target)
        self.wm_optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(world.parameters(), 1.0)
        self.wm_optimizer.step()
        return {"world_model_mse": float(loss.detach())}

    def set_parents(self, adjacency: np.ndarray) -> None:
        """Dyn-O estimates no graph over the given factors: nothing to take from one."""

    def config_json(self) -> str:
        return model_config_json("dyno", self.model.layout, self.config)

    def state_dict(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "updates": self.updates,
                "optimizers": {"autoencoder": self.ae_optimizer.state_dict(),
                               "slots": self.slot_trainer.optimizer.state_dict(),
                               "world_model": self.wm_optimizer.state_dict()},
                "slot_updates": self.slot_trainer.updates, "mask_generator": self.slot_trainer.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        state = copy.deepcopy(state)
        self.model.load_state_dict(state["model"])
        self.ae_optimizer.load_state_dict(state["optimizers"]["autoencoder"])
        self.slot_trainer.optimizer.load_state_dict(state["optimizers"]["slots"])
        self.wm_optimizer.load_state_dict(state["optimizers"]["world_model"])
        self.updates, self.slot_trainer.updates = int(state["updates"]), int(state["slot_updates"])
        self.slot_trainer.generator.set_state(state["mask_generator"])
        self.model.slots.autoencoder.requires_grad_(self.updates < self.config.ae_updates)
        if self.phase == "world_model":
            self.model.slots.requires_grad_(False)


@dataclass(frozen=True)
class SlotScores:
    """The ``slots`` role: FG-ARI of the model's slots on ``frames`` frames of unseen states, no masks."""

    frames: int = 512

    def scores(self, model: DynOModel, spec: EnvSpec) -> dict[str, Any]:
        render = model.renderer()
        render.reset(seed=SCORE_SEED)
        frames, labels = render.render_states(render.sample_states(self.frames))
        model.eval()
        segments = torch.cat([model.slots.segment(torch.from_numpy(frames[i : i + 128]))
                              for i in range(0, len(frames), 128)])
        return {"fg_ari": mean_fg_ari(labels, segments.numpy()), "frames": self.frames,
                "frame_size": model.config.frame_size, "num_slots": model.slots.config.num_slots,
                "env": spec.env_id, "settings": asdict(model.config),
                "evaluation": "final model, FG-ARI over foreground pixels of frames of unseen states, no masks "
                              "at inference (Table 7.1's metric)"}
