"""FLAM (chapter 8) as one trainable model for the dynamics-learner: the FSQ autoencoder (eq. 8.1) and
the factored latent action model (eqs. 8.2-8.6, :mod:`causal.flam`), trained on the run's transitions.

The learner's bus carries transitions, not frames (frames go to the factor-extractor, which in a run
with ``--label-latent-actions`` labels them with this model's latent actions:
:mod:`services.factor_extractor.latent`), so, as Dyn-O's trainer does, the trainer draws its frames
itself: each replayed transition's state and next state (the agents' grid positions) are drawn with ``multigrid-agents``' renderer
(:meth:`envs.multigrid_agents.MultiGridAgentsEnv.render_positions`), with the renderer's exact
segments as the optional mask prior. Phases by update count, Algorithm 9's order:

1. ``ae_updates``: the FSQ autoencoder by reconstruction (eq. 8.1), then frozen;
2. then: FLAM on eq. 8.6, by default one clip of two frames (s, s') per transition: the factorizer's
   temporal attention then sees one past frame in training, the whole history in the rollouts that
   score it (docs/deviations.md). With ``clip_frames`` T > 2 the learner cuts clips of T consecutive
   states from its replay (:meth:`causal.replay.ReplayBuffer.sample_clips`), as the chapter's clips.

Every ``live_every`` latent-action updates the trainer scores its model on a few fixed unseen videos
(:func:`latent_action_scores`: 10-step PSNR, DCI, each slot's KL) and returns the figures with that
update's losses (``live_*`` keys), for the learner's beats and metrics: the live page's per-slot
latent actions. :class:`LatentActionScores` is the method's ``latent_actions`` role: the same scores of
the final model on 100 unseen videos, which a run's ``summary.json`` carries as ``latent_actions``.
"""
from __future__ import annotations

import copy
import json
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from causal.dci import DCI, dci, position_dci
from causal.factored import FactorLayout
from causal.flam import FLAM, FLAMConfig, LAMTrainer, encode_clips, psnr, rollout
from causal.flam_nets import FSQAutoencoder, gaussian_kl
from causal.method import layout_from_config, model_config_json
from causal.schedules import cosine_lr
from causal.slots import FEATURE_STRIDE, frames_to_tensor
from envs.multigrid_agents import NUM_MOVES, MultiGridAgentsEnv, displacement_codes, record_videos
from proto.messages import EnvSpec
from proto.settings import doc

SCORE_SEED = 20_000
"""Unseen videos come from episodes seeded from here on: seeds no run's env-workers draw from."""
FSQ_LEVELS = (5, 5, 5, 5)
"""FSQ levels of the feature channels (d_e = 4), as ``benchmarks.flam_table`` and results.md use."""


@dataclass(frozen=True)
class FLAMRunConfig:
    """FLAM (ch. 8) in a run: the autoencoder phase, the latent action model, the live scores.
    Defaults are results.md's Table 8.1 run (broadcast aggregator, annealed mask prior) with, since
    2026-12-07, the mask prior's binding term (weight 1), a 3,000-update autoencoder and the prior
    annealed over 12,000 updates: on seed 1 at the same load they took the run's latent actions against
    the actions from DCI D/C 0.05/0.05 to 0.76/0.73 (0.42/0.34 in a second run) and its slots against the
    positions from 0.50/0.46 to 0.83/0.81; 4 of 5 seeds bind (results.md, "A run with the binding term").
    Since the twenty-sixth session (2026-12-07) also beta_KL 3e-2 on clips of 4 frames with the learning
    rate decayed over 20,000 updates: on seeds 0-3 the latent actions read the actions at D/C
    0.50-0.62/0.45-0.58 (their ceiling, the observed moves, 0.80) where beta_KL 1e-3 gave 0.18/0.17 on
    seed 3, at 57-59 dB of prediction; at 3e-2 on clips of 2 frames runs collapse (results.md, "beta_KL
    with the binding term"). ``mask_prior`` none needs ``mask_binding`` 0. A run directory from before
    resumes only with the old values given (``--flam-beta-kl 1e-3``; before the binding term also
    ``--flam-mask-binding 0 --flam-ae-updates 300 --flam-lam-updates 1200``)."""

    num_slots: int = doc(0, "K: slots, each with its own latent action; 0 = agents + 1 (one per agent and "
                            "the background; the correlated variant's K = 3 + 1 is --flam-num-slots 4 with "
                            "--flam-mask-prior none --flam-mask-binding 0)")
    slot_dim: int = doc(32, "D: size of a slot and of the attention blocks")
    action_dim: int = doc(8, "d_a: size of one slot's latent action")
    iterations: int = doc(3, "slot-attention iterations, each followed by temporal self-attention")
    beta_kl: float = doc(3e-2, "beta_KL of eq. 8.6 (the chapter's runs 1e-3; 3e-2 with 4-frame clips here)")
    aggregator: str = doc("broadcast", "broadcast (the slots alone draw e^_{t+1}) or cross-attention (the "
                                       "chapter's: e_t's tokens attend to the predicted slots)",
                          choices=("broadcast", "cross-attention"))
    temporal_attention: bool = doc(True, "causal temporal self-attention in the factorizer (eqs. 8.2-8.3); "
                                         "false: Table 8.5's ablation (SAVi-style slots)")
    coupling: str = doc("per-slot", "per-slot (eqs. 8.4-8.5) or global (Table 8.5's Global-Coupled FLAM)",
                        choices=("per-slot", "global"))
    mask_prior: str = doc("annealed", "annealed: Dyn-O's prior from the renderer's segments, dropped with "
                                      "probability log(1+u)/log(1+U) over lam_updates; none: no masks",
                          choices=("annealed", "none"))
    mask_binding: float = doc(1.0, "weight of the mask prior's binding term (FLAMConfig.mask_binding): the "
                                   "slot attention without the masks learns to bind as they do (0: they only "
                                   "restrict it, as in the chapter; must be 0 with --flam-mask-prior none)")
    ae_updates: int = doc(3000, "phase 1: FSQ autoencoder updates (eq. 8.1; then frozen)")
    lam_updates: int = doc(12000, "U of the mask prior's schedule (latent-action updates until masks are never given)")
    ae_lr: float = doc(2e-3, "Adam learning rate of the autoencoder")
    lr: float = doc(2e-3, "Adam learning rate of the latent action model")
    lr_decay_updates: int = doc(20000, "cosine decay of the latent action model's learning rate from lr to "
                                   "lr_final over this many latent-action updates, constant after (0: "
                                   "constant lr; not in the chapter)")
    lr_final: float = doc(1e-4, "the latent action model's learning rate at the end of the decay")
    clip_frames: int = doc(4, "frames per training clip: 2, one transition each; more: "
                              "that many consecutive states cut from the replay, as the chapter's clips "
                              "(the factorizer's temporal attention then sees that much history)")
    batch_size: int = doc(16, "clips per update (autoencoder: every frame of them; FLAM: the clips)")
    live_every: int = doc(200, "latent-action updates between live scores on fixed unseen videos (0: none)")
    live_videos: int = doc(16, "unseen videos of the live scores")
    horizon: int = doc(10, "prediction steps of the PSNR (live and final)")

    def __post_init__(self) -> None:
        if min(self.slot_dim, self.action_dim, self.iterations, self.batch_size, self.live_videos, self.horizon) < 1:
            raise ValueError("FLAM sizes, iterations, batch size, live videos and horizon must be positive")
        if min(self.num_slots, self.ae_updates, self.lam_updates, self.live_every) < 0:
            raise ValueError("num_slots, ae_updates, lam_updates and live_every must not be negative")
        if self.slot_dim % 4:
            raise ValueError(f"slot_dim must be a multiple of 4 (attention heads), got {self.slot_dim}")
        if self.clip_frames < 2:
            raise ValueError(f"clip_frames must be at least 2 (one transition), got {self.clip_frames}")
        if self.lr_decay_updates < 0:
            raise ValueError(f"lr_decay_updates must not be negative, got {self.lr_decay_updates}")
        if not all(math.isfinite(x) and x > 0 for x in (self.ae_lr, self.lr, self.lr_final)):
            raise ValueError("FLAM learning rates must be positive finite numbers")
        if not (math.isfinite(self.beta_kl) and self.beta_kl >= 0):
            raise ValueError(f"beta_kl must be a finite number >= 0, got {self.beta_kl}")
        if not (math.isfinite(self.mask_binding) and self.mask_binding >= 0):
            raise ValueError(f"mask_binding must be a finite number >= 0, got {self.mask_binding}")
        if self.mask_binding > 0 and self.mask_prior == "none":
            raise ValueError("mask_binding needs the annealed mask prior (mask_prior none gives no masks to bind to): "
                             "set --flam-mask-binding 0 with --flam-mask-prior none")
        if self.aggregator not in ("broadcast", "cross-attention"):
            raise ValueError(f"aggregator must be 'broadcast' or 'cross-attention', got {self.aggregator!r}")
        if self.coupling not in ("per-slot", "global"):
            raise ValueError(f"coupling must be 'per-slot' or 'global', got {self.coupling!r}")
        if self.mask_prior not in ("annealed", "none"):
            raise ValueError(f"mask_prior must be 'annealed' or 'none', got {self.mask_prior!r}")

    def lam(self, num_agents: int) -> FLAMConfig:
        return FLAMConfig(num_slots=self.num_slots or num_agents + 1, slot_dim=self.slot_dim,
                          action_dim=self.action_dim, iterations=self.iterations, levels=FSQ_LEVELS,
                          beta_kl=self.beta_kl, aggregator=self.aggregator, lr=self.lr,
                          lr_decay_updates=self.lr_decay_updates, lr_final=self.lr_final, batch_size=self.batch_size,
                          temporal_attention=self.temporal_attention, coupling=self.coupling,
                          mask_binding=self.mask_binding)


def multigrid_geometry(layout: FactorLayout) -> tuple[int, int]:
    """Agents and grid side of a MultiGrid-agents layout (``agent{i}.x``, ``agent{i}.y``); ``ValueError``
    for any other, which FLAM's trainer cannot draw."""
    n = layout.num_factors // 2
    expected = tuple(f"agent{i}.{axis}" for i in range(n) for axis in "xy")
    if n < 1 or tuple(layout.names) != expected or len(set(layout.sizes)) != 1:
        raise ValueError("FLAM draws MultiGrid-agents states only (factors agent<i>.x, agent<i>.y on one grid)")
    return n, int(layout.sizes[0])


def check_layout(layout: FactorLayout, config: FLAMRunConfig) -> None:
    """``ValueError`` unless ``layout`` is a MultiGrid-agents one whose agents ``config``'s slots can take:
    the annealed mask prior gives each agent's segment and the background a slot of its own."""
    agents, _ = multigrid_geometry(layout)
    if config.mask_prior == "annealed" and 0 < config.num_slots < agents + 1:
        raise ValueError(f"--flam-mask-prior annealed gives each of the {agents} agents and the background a slot of "
                         f"its own: --flam-num-slots must be 0 or >= {agents + 1}, got {config.num_slots} (fewer "
                         f"slots, e.g. the correlated variant's K = 3 + 1, run with --flam-mask-prior none "
                         f"--flam-mask-binding 0)")


class FLAMModel(nn.Module):
    """The FSQ autoencoder and FLAM of one MultiGrid-agents layout (one feature token per grid cell)."""

    def __init__(self, layout: FactorLayout, config: FLAMRunConfig) -> None:
        super().__init__()
        self.layout, self.config = layout, config
        check_layout(layout, config)
        self.num_agents, self.grid_size = multigrid_geometry(layout)
        self.autoencoder = FSQAutoencoder(FSQ_LEVELS)
        self.lam = FLAM(config.lam(self.num_agents), self.grid_size ** 2)

    def renderer(self, correlated: bool = False) -> MultiGridAgentsEnv:
        return MultiGridAgentsEnv(num_agents=self.num_agents, grid_size=self.grid_size,
                                  cell_pixels=FEATURE_STRIDE, correlated=correlated)

    def features(self, frames: torch.Tensor) -> torch.Tensor:
        """Frozen features ``[B, T, n, d_e]`` of clips (uint8 ``[B, T, H, W, 3]``)."""
        return encode_clips(self.autoencoder, frames)


def model_from_config(data: dict[str, Any]) -> FLAMModel:
    return FLAMModel(layout_from_config(data), FLAMRunConfig(**data["flam"]))


def token_labels(labels: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Each feature token's segment ``[..., n]`` of pixel labels ``[..., H, W]`` (one token per cell)."""
    labels = torch.as_tensor(np.asarray(labels))
    return labels[..., ::FEATURE_STRIDE, ::FEATURE_STRIDE].flatten(-2).long()


def observed_move_dci(positions: np.ndarray, actions: np.ndarray) -> DCI:
    """DCI of each agent's observed move (:func:`envs.multigrid_agents.displacement_codes` of ``positions``
    ``[E, T + 1, N, 2]``) against the actions ``[E, T, N]``: the ceiling of the latent actions' DCI."""
    return dci(torch.from_numpy(displacement_codes(positions)), torch.from_numpy(np.asarray(actions)).flatten(0, 1),
               classes=NUM_MOVES)


@torch.no_grad()
def latent_action_scores(model: FLAMModel, videos: dict[str, np.ndarray], ceiling: bool = True) -> dict[str, Any]:
    """The scores of Tables 8.1-8.2 on ``videos`` (:func:`envs.multigrid_agents.record_videos`): PSNR of
    the rollout over the whole video (latent actions inferred from the true frames, predictions fed
    back), DCI of the latent actions' posterior means against the agents' actions (each slot one
    factor: ``dci_d``, ``dci_c``, ``dci_i``), the same DCI of each agent's observed move on the same
    videos (:func:`envs.multigrid_agents.displacement_codes`: the ceiling of the latent actions', since
    a blocked move looks like a stay; ``dci_*_ceiling``), DCI of the slots' states against the agents' positions
    (Table 8.2's own reading, each slot one factor, each agent's x and y one ground-truth factor:
    ``dci_d_positions``, ...), and each slot's mean KL to the prior (nats per transition: what its
    latent action carries)."""
    model.eval()
    frames = torch.from_numpy(videos["frames"])
    features = model.features(frames)
    predicted = rollout(model.lam, features, model.autoencoder.fsq)
    images = model.autoencoder.decode(predicted.flatten(0, 1), model.grid_size)
    target = frames_to_tensor(frames[:, 1:].flatten(0, 1))
    shape = (len(frames), -1) + images.shape[1:]
    slots, _ = model.lam.factorizer(features)
    k, d = slots.shape[2:]
    mu, log_sigma = model.lam.idm(slots[:, :-1].reshape(-1, k, d), slots[:, 1:].reshape(-1, k, d))
    scores = dci(mu, torch.from_numpy(videos["actions"]).flatten(0, 1), classes=NUM_MOVES)
    positions = position_dci(slots.flatten(0, 1), torch.from_numpy(videos["positions"]).flatten(0, 1), model.grid_size)
    bound = {}
    if ceiling:  # the same for every model on these videos: the final scores carry it, the live ones do not
        top = observed_move_dci(videos["positions"], videos["actions"])
        bound = {"dci_d_ceiling": top.disentanglement, "dci_c_ceiling": top.completeness,
                 "dci_i_ceiling": top.informativeness}
    return {"psnr": float(psnr(images.view(shape), target.view(shape)).mean()), "dci_d": scores.disentanglement,
            "dci_c": scores.completeness, "dci_i": scores.informativeness, **bound,
            "dci_d_positions": positions.disentanglement, "dci_c_positions": positions.completeness,
            "dci_i_positions": positions.informativeness,
            "slot_kl": [float(v) for v in gaussian_kl(mu, log_sigma).mean(0)]}


class FLAMTrainer:
    """FLAM's two phases with the dynamics-learner's trainer interface: ``update(s, a, s')`` on clips of
    two frames, or, with ``clip_frames`` above 2, ``update_clips(states)`` on clips of consecutive
    states the learner cuts from its replay."""

    def __init__(self, layout: FactorLayout, config: FLAMRunConfig, seed: int) -> None:
        torch.manual_seed(seed)
        self.config, self.batch_size, self.clip_frames = config, config.batch_size, config.clip_frames
        self.model = FLAMModel(layout, config)
        self.render = self.model.renderer()
        self.ae_optimizer = torch.optim.Adam(self.model.autoencoder.parameters(), lr=config.ae_lr)
        self.lam_trainer = LAMTrainer(self.model.lam, seed=seed, mask_prior=config.mask_prior,
                                      total_updates=config.lam_updates)
        self.live = record_videos(self.render, config.live_videos, config.horizon, seed=SCORE_SEED + 50_000)
        self.updates = 0

    @property
    def phase(self) -> str:
        return "autoencoder" if self.updates < self.config.ae_updates else "latent_actions"

    @property
    def lr(self) -> float:
        if self.phase == "autoencoder":
            return self.config.ae_lr
        return cosine_lr(self.config.lr, self.config.lr_final, self.lam_trainer.updates, self.config.lr_decay_updates)

    def frames(self, states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Frames (uint8 ``[..., H, W, 3]``) and pixel labels of states ``[..., 2N]``, drawn by the renderer."""
        flat = states.detach().cpu().numpy().reshape(-1, self.model.num_agents, 2).round().astype(np.int64)
        frames, labels = self.render.render_positions(flat)
        lead = tuple(states.shape[:-1])
        return (torch.from_numpy(frames).view(lead + frames.shape[1:]),
                torch.from_numpy(labels).view(lead + labels.shape[1:]))

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        """One update on clips of two frames (s, s'); see :meth:`update_clips`."""
        return self.update_clips(torch.stack([state, next_state], dim=1))

    def update_clips(self, states: torch.Tensor) -> dict[str, float]:
        """One update of the current phase on clips of consecutive states ``[B, T, 2N]``; returns its
        losses, the phase (0, 1) and, every ``live_every`` latent-action updates, the live scores
        (``live_*``). The autoencoder trains on every frame of the clips."""
        phase = self.phase
        if phase == "autoencoder":
            stats = self._autoencoder_step(states.flatten(0, 1))
        else:
            frames, labels = self.frames(states)
            stats = self.lam_trainer.update(self.model.features(frames), token_labels(labels))
            every = self.config.live_every
            if every and (self.lam_trainer.updates - 1) % every == 0:
                stats.update(self.live_scores())
        self.updates += 1
        return {**stats, "phase": float(phase == "latent_actions")}

    def _autoencoder_step(self, states: torch.Tensor) -> dict[str, float]:
        images = frames_to_tensor(self.frames(states)[0])
        autoencoder = self.model.autoencoder
        loss = F.mse_loss(autoencoder(images), images)
        self.ae_optimizer.zero_grad()
        loss.backward()
        self.ae_optimizer.step()
        if self.updates + 1 == self.config.ae_updates:
            autoencoder.requires_grad_(False)
        return {"autoencoder_mse": float(loss.detach())}

    def live_scores(self) -> dict[str, float]:
        """:func:`latent_action_scores` of the model now on the fixed live videos, as ``live_*`` stats."""
        scores = latent_action_scores(self.model, self.live, ceiling=False)
        self.model.lam.train()
        return {**{f"live_{k}": scores[k] for k in ("psnr", "dci_d", "dci_c", "dci_i")},
                **{f"live_slot{k}_kl": v for k, v in enumerate(scores["slot_kl"])}}

    def set_parents(self, adjacency: np.ndarray) -> None:
        """FLAM estimates no graph over the given factors: nothing to take from one."""

    def config_json(self) -> str:
        return model_config_json("flam", self.model.layout, self.config)

    def state_dict(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "updates": self.updates,
                "optimizers": {"autoencoder": self.ae_optimizer.state_dict(),
                               "latent_actions": self.lam_trainer.optimizer.state_dict()},
                "lam_updates": self.lam_trainer.updates, "mask_generator": self.lam_trainer.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        state = copy.deepcopy(state)
        self.model.load_state_dict(state["model"])
        self.ae_optimizer.load_state_dict(state["optimizers"]["autoencoder"])
        self.lam_trainer.optimizer.load_state_dict(state["optimizers"]["latent_actions"])
        self.updates, self.lam_trainer.updates = int(state["updates"]), int(state["lam_updates"])
        self.lam_trainer.generator.set_state(state["mask_generator"])
        self.model.autoencoder.requires_grad_(self.updates < self.config.ae_updates)


@dataclass(frozen=True)
class LatentActionScores:
    """The ``latent_actions`` role: Tables 8.1-8.2's scores of the final model on ``videos`` unseen videos."""

    videos: int = 100

    def scores(self, model: FLAMModel, spec: EnvSpec) -> dict[str, Any]:
        correlated = bool(json.loads(spec.config_json or "{}").get("correlated", False))
        render = model.renderer(correlated)
        scores = latent_action_scores(model, record_videos(render, self.videos, model.config.horizon, SCORE_SEED))
        return {**scores, "videos": self.videos, "horizon": model.config.horizon,
                "num_slots": model.lam.config.num_slots, "env": spec.env_id, "settings": asdict(model.config),
                "evaluation": f"final model on {self.videos} unseen videos of a uniformly random policy: PSNR of "
                              f"{model.config.horizon}-step predictions (latent actions inferred from the true frames, "
                              "predictions fed back; Table 8.1's protocol), DCI of the latent actions' posterior "
                              "means against the agents' actions (dci_*), DCI of the slots' states against the "
                              "agents' positions (dci_*_positions, Table 8.2's reading), each slot's KL (nats)"}
