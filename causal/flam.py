"""FLAM, the factored latent action model (dissertation chapter 8, section 8.2), and its monolithic
baseline of equal latent capacity.

Phase 1 (eq. 8.1): an FSQ autoencoder trained on frames, then frozen (:func:`fit_autoencoder`).
Phase 2 (eqs. 8.2-8.6), on the frozen features ``e_{1:T}`` of a clip:

    xi_{1:T} = Factorizer(e_{1:T})                                  (eqs. 8.2-8.3)
    alpha^i_t ~ q = N(M_mu, M_sigma)(IDM(xi_t^{1:K}, xi_{t+1}^i))    (eq. 8.4)
    xi^_{t+1}^i = FDM(xi_t^{1:K}, alpha^i_t)                         (eq. 8.5)
    e^_{t+1} = Aggregator(e_t, xi^_{t+1}^{1:K})
    L = ||e_{t+1} - e^_{t+1}||^2 + beta_KL sum_i KL[q(alpha^i_t) || N(0, I)]   (eq. 8.6)

The monolithic model (AdaWorld-like, the chapter's baseline) has no slots: one Gaussian latent of
size ``K * d_a`` inferred from the tokens of ``e_t`` and ``e_{t+1}``, and a forward model over the
tokens of ``e_t`` given it. Both predict ``T`` steps by feeding back their (FSQ-snapped) predictions
with latent actions inferred from the true frames (:func:`rollout`), the chapter's protocol.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Protocol

import torch
import torch.nn.functional as F
from torch import nn

from causal.flam_nets import (FSQ, Aggregator, AttentionBlock, BroadcastAggregator, Factorizer, ForwardDynamics, FSQAutoencoder,
                              InverseDynamics, TokenEmbedding, gaussian_kl, posterior_scale)
from causal import slots
from causal.schedules import cosine_lr
from causal.slots import SlotConfig, SlotDecoder, drop_probability, frames_to_tensor
from proto.settings import doc


@dataclass(frozen=True)
class FLAMConfig:
    """FLAM (ch. 8): sizes, the KL weight and the optimiser of the latent action model."""

    num_slots: int = doc(4, "K: slots (factors), each with its own latent action")
    slot_dim: int = doc(64, "D: size of a slot and of the attention blocks")
    action_dim: int = doc(8, "d_a: size of one slot's latent action (the monolithic model gets K * d_a)")
    iterations: int = doc(3, "slot-attention iterations, each followed by temporal self-attention")
    levels: tuple[int, ...] = doc((5, 5, 5, 5), "FSQ levels per feature channel (d_e = their count)")
    beta_kl: float = doc(1e-3, "beta_KL of eq. 8.6")
    aggregator: str = doc("cross-attention", "cross-attention: e_t's tokens attend to the predicted slots "
                                             "(the chapter's); broadcast: the slots alone draw e^_{t+1} "
                                             "through a spatial-broadcast decoder", choices=("cross-attention", "broadcast"))
    slot_reconstruction: float = doc(0.0, "weight of an added slot-decoder reconstruction of e_t from xi_t "
                                          "(Dyn-O's eq. 7.1 term; 0: eq. 8.6 alone, the chapter's)")
    temporal_attention: bool = doc(True, "causal temporal self-attention in the factorizer (eqs. 8.2-8.3); "
                                         "False: Table 8.5's ablation, SAVi-style slots started from the "
                                         "previous frame's")
    coupling: str = doc("per-slot", "per-slot: alpha^i from all slots at t and slot i at t+1, slot i's next "
                                    "value from all slots at t and alpha^i (eqs. 8.4-8.5); global: Table "
                                    "8.5's Global-Coupled FLAM (the IDM reads every slot at t and t+1, the "
                                    "FDM every latent action)", choices=("per-slot", "global"))
    static_background: bool = doc(False, "slot 0 (the background's) has no latent action: its alpha is 0 "
                                          "and its posterior N(0, I), so its next value comes from the slots "
                                          "at t alone and a moving object it holds is left unexplained (not in "
                                          "the chapter, whose slots are all alike)")
    action_levels: tuple[int, ...] = doc((), "FSQ levels of each slot's latent action (one per channel, so "
                                            "d_a = their count): alpha^i is the IDM's mean quantised, with no "
                                            "noise and no KL term, a hard bottleneck of prod(levels) codes per "
                                            "slot (not in the chapter, whose alpha is Gaussian); (): Gaussian")
    mask_binding: float = doc(0.0, "weight of the mask prior's binding term: the cross-entropy of the slot "
                                   "attention computed without the mask against the slots the mask allows, "
                                   "per segment, on the clips whose masks are not dropped (0: the prior only "
                                   "restricts the attention, Dyn-O's; > 0 also teaches the slots to bind so "
                                   "without it; not in the chapter)")
    lr: float = doc(1e-3, "Adam learning rate")
    lr_decay_updates: int = doc(0, "cosine decay of the learning rate from lr to lr_final over this many "
                                   "updates, constant after (0: constant lr; not in the chapter)")
    lr_final: float = doc(1e-4, "learning rate at the end of the decay")
    batch_size: int = doc(16, "clips per update")

    def __post_init__(self) -> None:
        if min(self.num_slots, self.slot_dim, self.action_dim, self.iterations, self.batch_size) < 1:
            raise ValueError("FLAM sizes, iterations and batch size must be positive")
        if self.aggregator not in ("cross-attention", "broadcast"):
            raise ValueError(f"aggregator must be 'cross-attention' or 'broadcast', got {self.aggregator!r}")
        if self.coupling not in ("per-slot", "global"):
            raise ValueError(f"coupling must be 'per-slot' or 'global', got {self.coupling!r}")
        if self.action_levels and len(self.action_levels) != self.action_dim:
            raise ValueError(f"action_levels {self.action_levels} give d_a = {len(self.action_levels)}, "
                             f"but action_dim is {self.action_dim}")
        if self.lr_decay_updates < 0 or not self.lr_final > 0:
            raise ValueError("lr_decay_updates must be >= 0 and lr_final > 0")
        if not (self.lr > 0 and self.beta_kl >= 0 and self.slot_reconstruction >= 0 and self.mask_binding >= 0) \
                or self.slot_dim % 4:
            raise ValueError("lr must be > 0, beta_kl, slot_reconstruction and mask_binding >= 0 and slot_dim "
                             "a multiple of 4")


class LAMOutput(NamedTuple):
    predicted: torch.Tensor
    """e^_{2:T} ``[B, T-1, n, d_e]``."""
    mu: torch.Tensor
    log_sigma: torch.Tensor
    """Posterior of the latent actions: FLAM ``[B, T-1, K, d_a]``, monolithic ``[B, T-1, 1, K d_a]``."""
    attention: torch.Tensor | None
    """FLAM's slot attention ``[B, T, K, n]`` (None for the monolithic model)."""
    reconstructed: torch.Tensor | None = None
    """FLAM's slot-decoder reconstruction of e_{1:T} ``[B, T, n, d_e]`` when ``slot_reconstruction > 0``."""
    binding: torch.Tensor | None = None
    """FLAM's mask binding term (a scalar, :meth:`causal.flam_nets.Factorizer.bind`) when masks were given."""


class LatentActionModel(Protocol):
    def forward(self, features: torch.Tensor, sample: bool = True,
                allowed: torch.Tensor | None = None) -> LAMOutput: ...
    def infer(self, features: torch.Tensor) -> torch.Tensor: ...
    def step(self, history: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor: ...


def sample_latent(mu: torch.Tensor, log_sigma: torch.Tensor, sample: bool) -> torch.Tensor:
    return mu + torch.exp(log_sigma) * torch.randn_like(mu) if sample else mu


class FLAM(nn.Module):
    """Factorizer, per-slot IDM and FDM, and aggregator, on frozen feature tokens ``[B, T, n, d_e]``."""

    def __init__(self, config: FLAMConfig, num_tokens: int) -> None:
        super().__init__()
        d_e, d = len(config.levels), config.slot_dim
        self.config = config
        self.factorizer = Factorizer(d_e, num_tokens, config.num_slots, d, config.iterations, config.temporal_attention)
        coupled = config.coupling == "global"
        self.idm = InverseDynamics(d, config.action_dim, coupled)
        self.fdm = ForwardDynamics(d, config.action_dim, coupled)
        self.aggregator = (BroadcastAggregator if config.aggregator == "broadcast" else Aggregator)(d_e, num_tokens, d)
        self.slot_decoder = (SlotDecoder(num_tokens, d_e, SlotConfig(slot_dim=d, decoder_hidden=d))
                             if config.slot_reconstruction > 0 else None)
        self.action_fsq = FSQ(config.action_levels) if config.action_levels else None

    def forward(self, features: torch.Tensor, sample: bool = True, allowed: torch.Tensor | None = None) -> LAMOutput:
        slots, attention, binding = self.factorizer.bind(features, allowed)
        reconstructed = None
        if self.slot_decoder is not None:
            reconstructed = self.slot_decoder(slots.flatten(0, 1))[0].view_as(features)
        b, t, k, d = slots.shape
        current, nxt = slots[:, :-1].reshape(-1, k, d), slots[:, 1:].reshape(-1, k, d)
        mu, log_sigma = self._posterior(current, nxt)
        alpha = mu if self.action_fsq is not None else sample_latent(mu, log_sigma, sample)
        if self.config.static_background:
            alpha = torch.cat([torch.zeros_like(alpha[:, :1]), alpha[:, 1:]], dim=1)
        predicted_slots = self.fdm(current, alpha)
        predicted = self.aggregator(features[:, :-1].flatten(0, 1), predicted_slots)
        shape = (b, t - 1)
        return LAMOutput(predicted.view(shape + predicted.shape[1:]), mu.view(shape + mu.shape[1:]),
                         log_sigma.view(shape + mu.shape[1:]), attention, reconstructed,
                         None if allowed is None else binding)

    def infer(self, features: torch.Tensor) -> torch.Tensor:
        """Posterior means of the latent actions ``[B, T-1, K, d_a]`` of a clip's features."""
        return self.posterior(features)[0]

    def posterior(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The latent actions' posterior (eq. 8.4) of a clip's features ``[B, T, n, d_e]``: means and log
        standard deviations ``[B, T-1, K, d_a]``."""
        slots, _ = self.factorizer(features)
        k, d = slots.shape[2:]
        mu, log_sigma = self._posterior(slots[:, :-1].reshape(-1, k, d), slots[:, 1:].reshape(-1, k, d))
        shape = slots.shape[:1] + (-1,) + mu.shape[1:]
        return mu.view(shape), log_sigma.view(shape)

    def _posterior(self, current: torch.Tensor, nxt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The IDM's posterior ``[N, K, d_a]`` (eq. 8.4); with ``static_background``, slot 0's is N(0, I)
        (mean 0, log sigma 0: no KL, and alpha 0 where it is used). With ``action_levels`` the mean is the
        quantised code and the log sigma 0 (a point mass: :func:`lam_loss` then takes no KL)."""
        mu, log_sigma = self.idm(current, nxt)
        if self.action_fsq is not None:
            mu, log_sigma = self.action_fsq(mu), torch.zeros_like(log_sigma)
        if self.config.static_background:
            mu = torch.cat([torch.zeros_like(mu[:, :1]), mu[:, 1:]], dim=1)
            log_sigma = torch.cat([torch.zeros_like(log_sigma[:, :1]), log_sigma[:, 1:]], dim=1)
        return mu, log_sigma

    def step(self, history: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """e^_{t+1} ``[B, n, d_e]`` from the features so far ``[B, t, n, d_e]`` and alpha_t ``[B, K, d_a]``."""
        slots, _ = self.factorizer(history)
        return self.aggregator(history[:, -1], self.fdm(slots[:, -1], alpha))


class MonolithicLAM(nn.Module):
    """One latent action of size ``K * d_a`` for the whole scene (AdaWorld-like): the IDM reads the
    tokens of ``e_t`` and ``e_{t+1}`` and pools them with a learned query; the FDM adds the action to
    every token of ``e_t`` and runs self-attention over the tokens."""

    def __init__(self, config: FLAMConfig, num_tokens: int) -> None:
        super().__init__()
        if config.action_levels:
            raise ValueError("the monolithic model's latent is Gaussian: action_levels is FLAM's alone")
        d_e, d, size = len(config.levels), config.slot_dim, config.num_slots * config.action_dim
        self.config = config
        self.embed_pair = TokenEmbedding(2 * d_e, num_tokens, d)
        self.idm_tokens, self.idm_pool = AttentionBlock(d), AttentionBlock(d)
        self.query = nn.Parameter(torch.randn(1, 1, d) * d ** -0.5)
        self.to_mu, self.to_log_sigma = nn.Linear(d, size), posterior_scale(d, size)
        self.embed = TokenEmbedding(d_e, num_tokens, d)
        self.action_in = nn.Linear(size, d)
        self.fdm_tokens, self.fdm_out = AttentionBlock(d), AttentionBlock(d)
        self.out = nn.Linear(d, d_e)

    def posterior(self, current: torch.Tensor, nxt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pair = self.embed_pair(torch.cat([current, nxt], -1))
        tokens = self.idm_tokens(pair, pair)
        pooled = self.idm_pool(self.query.expand(len(tokens), 1, -1), tokens)
        return self.to_mu(pooled), self.to_log_sigma(pooled).clamp(-8.0, 4.0)

    def predict(self, current: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        tokens = self.embed(current) + self.action_in(alpha)
        tokens = self.fdm_tokens(tokens, tokens)
        return current + self.out(self.fdm_out(tokens, tokens))

    def forward(self, features: torch.Tensor, sample: bool = True, allowed: torch.Tensor | None = None) -> LAMOutput:
        """``allowed`` (a mask prior) is ignored: the monolithic model has no slots."""
        b, t = features.shape[:2]
        current, nxt = features[:, :-1].flatten(0, 1), features[:, 1:].flatten(0, 1)
        mu, log_sigma = self.posterior(current, nxt)
        predicted = self.predict(current, sample_latent(mu, log_sigma, sample))
        shape = (b, t - 1)
        return LAMOutput(predicted.view(shape + predicted.shape[1:]), mu.view(shape + mu.shape[1:]),
                         log_sigma.view(shape + mu.shape[1:]), None)

    def infer(self, features: torch.Tensor) -> torch.Tensor:
        mu, _ = self.posterior(features[:, :-1].flatten(0, 1), features[:, 1:].flatten(0, 1))
        return mu.view(features.shape[:1] + (-1,) + mu.shape[1:])

    def step(self, history: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        return self.predict(history[:, -1], alpha)


def lam_loss(features: torch.Tensor, out: LAMOutput, beta_kl: float,
             slot_reconstruction: float = 0.0, mask_binding: float = 0.0) -> tuple[torch.Tensor, dict[str, float]]:
    """Eq. 8.6 per transition, averaged over transitions: the squared error of the next features
    (summed over tokens and channels) plus beta_KL times the KL summed over slots; plus, when the
    model reconstructs, ``slot_reconstruction`` times the squared error of e_t from its slots; plus,
    when masks were given, ``mask_binding`` times the binding term (reported as ``mask_binding_ce``
    whatever its weight)."""
    prediction = (out.predicted - features[:, 1:]).pow(2).flatten(2).sum(-1).mean()
    kl = gaussian_kl(out.mu, out.log_sigma).sum(-1).mean()
    terms = {"prediction_sse": float(prediction.detach()), "kl": float(kl.detach())}
    loss = prediction + beta_kl * kl
    if out.reconstructed is not None:
        reconstruction = (out.reconstructed - features).pow(2).flatten(2).sum(-1).mean()
        loss = loss + slot_reconstruction * reconstruction
        terms["slot_reconstruction_sse"] = float(reconstruction.detach())
    if out.binding is not None:
        if mask_binding > 0:
            loss = loss + mask_binding * out.binding
        terms["mask_binding_ce"] = float(out.binding.detach())
    return loss, terms


MASK_PRIORS = ("none", "annealed", "foreground")
"""FLAM's priors on slot attention (:class:`LAMTrainer`)."""


class LAMTrainer:
    """Adam on eq. 8.6 for FLAM or the monolithic model, on clips of frozen features.

    ``mask_prior="annealed"`` is Dyn-O's prior (causal/slots.py) applied to FLAM's slot attention:
    slot ``k`` sees only the tokens of segment ``k`` (token labels given to :meth:`update`), each clip
    dropping its masks with probability log(1 + u) / log(1 + U) at update u of ``total_updates``.
    ``mask_prior="foreground"`` is a weaker prior, annealed the same way, that says only *which tokens
    are objects*: slot 0 sees the background's tokens (segment 0), every other slot the tokens of any
    segment but 0, so the slots themselves decide which objects they share (not in the chapter; the
    correlated variant's test, where the segment-per-slot prior would give the answer away)."""

    def __init__(self, model: nn.Module, seed: int = 0, mask_prior: str = "none", total_updates: int = 0) -> None:
        if mask_prior not in MASK_PRIORS:
            raise ValueError(f"mask_prior must be one of {MASK_PRIORS}, got {mask_prior!r}")
        self.model, self.config = model, model.config
        self.mask_prior, self.total_updates = mask_prior, total_updates
        self.optimizer = torch.optim.Adam(model.parameters(), lr=self.config.lr)
        torch.manual_seed(seed)
        self.generator = torch.Generator().manual_seed(seed)
        self.updates = 0

    def masks_for(self, labels: torch.Tensor | None) -> torch.Tensor | None:
        """This update's attention masks ``[B, T, K, n]`` from token labels ``[B, T, n]``, or None."""
        if self.mask_prior == "none" or labels is None:
            return None
        if self.mask_prior == "foreground":
            foreground = labels[:, :, None, :] > 0
            slot = torch.arange(self.config.num_slots)[None, None, :, None]
            allowed = torch.where(slot == 0, ~foreground, foreground)
        else:
            allowed = F.one_hot(labels.long(), self.config.num_slots).permute(0, 1, 3, 2).bool()
        dropped = torch.rand(len(labels), generator=self.generator) < drop_probability(self.updates, self.total_updates)
        return allowed | dropped[:, None, None, None]

    def update(self, features: torch.Tensor, labels: torch.Tensor | None = None) -> dict[str, float]:
        """One step on a batch of clips ``[B, T, n, d_e]`` (token labels ``[B, T, n]`` for a mask prior)."""
        self.model.train()
        for group in self.optimizer.param_groups:
            group["lr"] = cosine_lr(self.config.lr, self.config.lr_final, self.updates, self.config.lr_decay_updates)
        out = self.model(features, allowed=self.masks_for(labels))
        beta_kl = 0.0 if self.config.action_levels else self.config.beta_kl
        loss, terms = lam_loss(features, out, beta_kl, self.config.slot_reconstruction, self.config.mask_binding)
        self.optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
        self.optimizer.step()
        self.updates += 1
        return {"loss": float(loss.detach()), **terms}


def fit_autoencoder(autoencoder: FSQAutoencoder, frames: torch.Tensor, updates: int, batch_size: int = 32,
                    lr: float = 2e-3, seed: int = 0) -> float:
    """Eq. 8.1 on frames (uint8 ``[N, H, W, 3]``), then freeze; the last reconstruction loss (Dyn-O's
    reconstruction loop, :func:`causal.slots.fit_autoencoder`, at FLAM's learning rate)."""
    return slots.fit_autoencoder(autoencoder, frames, updates, batch_size=batch_size, lr=lr, seed=seed)


@torch.no_grad()
def encode_clips(autoencoder: FSQAutoencoder, frames: torch.Tensor) -> torch.Tensor:
    """Frozen features ``[B, T, n, d_e]`` of clips of frames (uint8 ``[B, T, H, W, 3]``)."""
    tokens = autoencoder.encode(frames_to_tensor(frames.flatten(0, 1)))
    return tokens.view(frames.shape[:2] + tokens.shape[1:])


@torch.no_grad()
def rollout(model: LatentActionModel, features: torch.Tensor, fsq: FSQ) -> torch.Tensor:
    """``T - 1`` predicted features ``[B, T-1, n, d_e]`` of clips ``[B, T, n, d_e]``: latent actions
    inferred from the true clip, each prediction FSQ-snapped and fed back (autoregressive)."""
    alphas = model.infer(features)
    history = features[:, :1]
    for t in range(alphas.shape[1]):
        history = torch.cat([history, fsq.snap(model.step(history, alphas[:, t]))[:, None]], dim=1)
    return history[:, 1:]


def psnr(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of images in [0, 1] per clip ``[B, T, ...]`` (MSE over the clip, floored at 1e-10)."""
    mse = (predicted.clamp(0, 1) - target).pow(2).flatten(1).mean(1)
    return 10 * torch.log10(1.0 / mse.clamp_min(1e-10))
