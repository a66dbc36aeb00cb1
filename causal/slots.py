"""Dyn-O's slot representation (dissertation section 7.2.1, eq. 7.1): frames -> slots -> reconstruction.

    e = Enc(o),  xi = Slot-Attn(xi_init, e, m),  e^ = Slot-Dec(xi),  o^ = Dec(e^)
    L_slot = ||e - e^||^2 + ||o - o^||^2                                            (eq. 7.1)

- ``Enc``/``Dec``: a small convolutional autoencoder trained here on the frames first and then frozen
  (:class:`FrameAutoencoder`), in the place of the frozen Cosmos tokenizer (no pretrained weights can
  be downloaded here: a deviation, docs/deviations.md).
- ``Slot-Attn``: iterative slot attention (Locatello et al. 2020; section 2.7) from K learnable initial
  slots, batched, with a GRU and MLP refinement; an optional attention mask ``m`` lets slot ``k`` attend
  only to the feature tokens of segment ``k`` (the mask prior).
- ``Slot-Dec``: a spatial-broadcast decoder over feature tokens (each slot plus a learned position
  embedding -> a per-token MLP -> features and an alpha logit; the alphas, normalised over slots, mix
  the features and are the slots' masks).
- The mask prior: during training a frame's masks are dropped with probability
  log(1 + u) / log(1 + U) (u updates done of U), so at the end slots bind without masks and inference
  needs none. The renderer's exact masks (envs/chemical_pixels.py) stand in for SAM2's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from torch import nn

from proto.settings import doc

MASK_PRIORS = ("annealed", "none", "always")
MASK_ASSIGNMENTS = ("index", "matched")
TOKEN_MASKS = ("touch", "objects")
"""How a label map becomes the mask prior's allowed slots per token (:func:`token_masks`)."""
FEATURE_STRIDE = 4
"""Pixels per feature token along each side (the frame autoencoder halves the resolution twice)."""


@dataclass(frozen=True)
class SlotConfig:
    """Dyn-O's slot representation (eq. 7.1): sizes, optimiser and the mask-prior schedule."""

    num_slots: int = doc(5, "K: slots per frame (objects and background)")
    feature_dim: int = doc(16, "d_e: channels of the frame autoencoder's feature tokens")
    slot_dim: int = doc(32, "d_xi: size of one slot")
    attention_dim: int = doc(32, "d_SA: size of slot attention's queries and keys")
    iterations: int = doc(3, "T_SA: slot-attention refinement steps")
    decoder_hidden: int = doc(32, "hidden width of the slot decoder's per-token MLP")
    lr: float = doc(3e-3, "Adam learning rate of slot attention and the slot decoder (on a 16-frame "
                                 "batch, 300 updates gave FG-ARI 0.41 at 3e-3, 0.05 at 1e-3)")
    batch_size: int = doc(32, "frames per update")
    mask_prior: str = doc("annealed", "annealed: drop the masks with probability log(1+u)/log(1+U); "
                                      "none: never use them (SOLV); always: always (the oracle)", choices=MASK_PRIORS)
    token_mask: str = doc("touch", "which slots a token may take under the masks: touch (every segment with a pixel "
                                   "in it, the background's included) or objects (the objects with a pixel in it; "
                                   "the background slot only tokens no object touches)", choices=TOKEN_MASKS)
    mask_assignment: str = doc("index", "which slot gets which segment under the masks: index (segment k to "
                                        "slot k, the renderer's object order) or matched (each frame's "
                                        "segments to the slots that attend to them most without masks, by "
                                        "Hungarian matching: the masks group tokens but fix no slot order; "
                                        "not in the chapter, whose SAM2 segments have no order)",
                               choices=MASK_ASSIGNMENTS)
    mask_binding: float = doc(0.0, "weight of the mask prior's binding term: the cross-entropy of the slot "
                                   "attention computed without the masks against the slots they allow, per "
                                   "segment, on the frames whose masks are kept (0: the masks only restrict "
                                   "the attention, the chapter's; > 0 also teaches the slots to bind so "
                                   "without them; not in the chapter)")

    def __post_init__(self) -> None:
        if self.mask_assignment not in MASK_ASSIGNMENTS:
            raise ValueError(f"mask_assignment must be one of {MASK_ASSIGNMENTS}, got {self.mask_assignment!r}")
        if min(self.num_slots, self.feature_dim, self.slot_dim, self.attention_dim, self.iterations,
               self.decoder_hidden, self.batch_size) < 1 or not self.lr > 0:
            raise ValueError("slot sizes, iterations, batch size and lr must be positive")
        if self.mask_binding < 0:
            raise ValueError(f"mask_binding must be >= 0, got {self.mask_binding}")
        if self.mask_prior not in MASK_PRIORS:
            raise ValueError(f"mask_prior must be one of {MASK_PRIORS}, got {self.mask_prior!r}")
        if self.token_mask not in TOKEN_MASKS:
            raise ValueError(f"token_mask must be one of {TOKEN_MASKS}, got {self.token_mask!r}")


def drop_probability(updates_done: int, total_updates: int) -> float:
    """Chance of training a frame without its masks: log(1 + u) / log(1 + U) (0 at the start, 1 at the end)."""
    return math.log1p(min(updates_done, total_updates)) / math.log1p(total_updates) if total_updates > 0 else 1.0


def frames_to_tensor(frames: torch.Tensor) -> torch.Tensor:
    """uint8 ``[B, H, W, 3]`` frames -> float ``[B, 3, H, W]`` in [0, 1]."""
    return frames.permute(0, 3, 1, 2).float() / 255.0


def restrict_attention(logits: torch.Tensor, allowed: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The mask prior on slot-attention logits ``[M, K, n]``: the logits with the slots a token may not
    take at -1e9, and each token's binding cross-entropy ``[M, n]``, ``-log`` of the share the attention
    *without* the mask gives to the slots the mask allows (0 where the mask allows every slot or none,
    so on a dropped mask, and everywhere when ``allowed`` is None).

    Under a one-slot-per-token mask the restricted softmax is exactly 1 whatever the logits, so the
    attention's queries and keys learn nothing from the masked frames about which slot takes which
    object; the cross-entropy is what would teach them (:func:`balanced_binding`)."""
    if allowed is None:
        return logits, logits.new_zeros(logits.shape[0], logits.shape[2])
    masked = logits.masked_fill(~allowed, -1e9)
    restricted = allowed.any(dim=1) & ~allowed.all(dim=1)
    cross_entropy = torch.where(restricted, logits.logsumexp(dim=1) - masked.logsumexp(dim=1), 0.0)
    return masked, cross_entropy


def balanced_binding(cross_entropy: torch.Tensor, allowed: torch.Tensor | None) -> torch.Tensor:
    """A scalar from :func:`restrict_attention`'s cross-entropy ``[M, n]``: averaged over the tokens of each
    segment (the tokens a slot is allowed, where the mask restricts), then over the segments of every
    frame whose mask restricts any token, so a small object counts as much as the background and a frame
    whose mask is dropped counts not at all (0 when no frame has a mask)."""
    if allowed is None:
        return cross_entropy.new_zeros(())
    restricted = allowed.any(dim=1) & ~allowed.all(dim=1)
    owners = (allowed & restricted[:, None, :]).to(cross_entropy.dtype)  # [M, K, n]
    count = owners.sum(dim=-1)
    per_segment = (owners * cross_entropy[:, None, :]).sum(dim=-1) / count.clamp_min(1.0)
    present = count > 0
    return per_segment[present].sum() / present.sum().clamp_min(1)


def token_masks(labels: torch.Tensor, num_slots: int, stride: int = FEATURE_STRIDE, rule: str = "touch") -> torch.Tensor:
    """bool ``[B, K, n]``: which slots each feature token (a ``stride`` x ``stride`` pixel block) of the
    label maps ``[B, H, W]`` (0 the background, ``k`` object ``k - 1``) may go to.

    ``touch``: every segment with a pixel in the token. ``objects``: the objects with a pixel in it,
    the background only where no object has one. Objects smaller than a token (the sprite game's fish
    at 32x32) share nearly every token they touch with the background, which under ``touch`` takes
    them (it holds most of the token's pixels); under ``objects`` the object keeps them. Either way
    every token has an allowed slot."""
    if rule not in TOKEN_MASKS:
        raise ValueError(f"rule must be one of {TOKEN_MASKS}, got {rule!r}")
    if int(labels.max()) >= num_slots:
        raise ValueError(f"labels up to {int(labels.max())} need more than {num_slots} slots")
    onehot = F.one_hot(labels.long(), num_slots).permute(0, 3, 1, 2).float()
    allowed = (F.avg_pool2d(onehot, stride) > 0).flatten(2)
    if rule == "objects":
        allowed[:, 0] &= ~allowed[:, 1:].any(dim=1)
    return allowed


class FrameAutoencoder(nn.Module):
    """Enc/Dec of eq. 7.1: frames ``[B, 3, H, W]`` <-> feature tokens ``[B, d_e, H/4, W/4]``."""

    def __init__(self, feature_dim: int, width: int = 16) -> None:
        super().__init__()
        self.encoder = nn.Sequential(
            nn.Conv2d(3, width, 4, stride=2, padding=1), nn.ReLU(), nn.Conv2d(width, width, 3, padding=1),
            nn.ReLU(), nn.Conv2d(width, feature_dim, 4, stride=2, padding=1))
        self.decoder = nn.Sequential(
            nn.ConvTranspose2d(feature_dim, width, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=1), nn.ReLU(), nn.ConvTranspose2d(width, 3, 4, stride=2, padding=1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder(images))


class SlotAttention(nn.Module):
    """Iterative slot attention over tokens ``[B, n, d_in]`` from K learnable initial slots."""

    def __init__(self, input_dim: int, config: SlotConfig) -> None:
        super().__init__()
        k, d = config.num_slots, config.slot_dim
        self.iterations, self.scale = config.iterations, config.attention_dim ** -0.5
        self.initial = nn.Parameter(torch.randn(k, d) * d ** -0.5)
        self.norm_tokens, self.norm_slots = nn.LayerNorm(input_dim), nn.LayerNorm(d)
        self.to_q = nn.Linear(d, config.attention_dim, bias=False)
        self.to_k = nn.Linear(input_dim, config.attention_dim, bias=False)
        self.to_v = nn.Linear(input_dim, d, bias=False)
        self.gru = nn.GRUCell(d, d)
        self.mlp = nn.Sequential(nn.LayerNorm(d), nn.Linear(d, 2 * d), nn.ReLU(), nn.Linear(2 * d, d))

    def forward(self, tokens: torch.Tensor, allowed: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Slots ``[B, K, d_xi]`` and the last attention ``[B, K, n]`` (normalised over slots);
        ``allowed`` (bool ``[B, K, n]``) is the mask prior: slot ``k`` sees only its tokens."""
        slots, attention, _ = self.bind(tokens, allowed)
        return slots, attention

    def bind(self, tokens: torch.Tensor, allowed: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`forward`'s slots and attention, and the mask's binding term (a scalar): each token's
        cross-entropy of the attention without the mask against the slots the mask allows, averaged over
        the iterations, then by :func:`balanced_binding` (0 without a mask)."""
        tokens = self.norm_tokens(tokens)
        keys, values = self.to_k(tokens), self.to_v(tokens)
        slots = self.initial.expand(len(tokens), -1, -1)
        binding = keys.new_zeros(keys.shape[:2])
        for _ in range(self.iterations):
            logits = torch.einsum("bkd,bnd->bkn", self.to_q(self.norm_slots(slots)), keys) * self.scale
            logits, token_binding = restrict_attention(logits, allowed)
            binding = binding + token_binding / self.iterations
            attention = logits.softmax(dim=1)
            weights = attention / (attention.sum(dim=2, keepdim=True) + 1e-8)
            updates = weights @ values
            slots = self.gru(updates.flatten(0, 1), slots.flatten(0, 1)).view_as(slots)
            slots = slots + self.mlp(slots)
        return slots, attention, balanced_binding(binding, allowed)


class SlotDecoder(nn.Module):
    """Slot-Dec: each slot broadcast over the ``n`` token positions -> features and an alpha logit."""

    def __init__(self, num_tokens: int, feature_dim: int, config: SlotConfig) -> None:
        super().__init__()
        self.position = nn.Parameter(torch.randn(num_tokens, config.slot_dim) * 0.02)
        h = config.decoder_hidden
        self.mlp = nn.Sequential(nn.Linear(config.slot_dim, h), nn.ReLU(), nn.Linear(h, h), nn.ReLU(),
                                 nn.Linear(h, feature_dim + 1))

    def forward(self, slots: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mixed features ``[B, n, d_e]`` and the alpha masks ``[B, K, n]`` (a softmax over slots)."""
        out = self.mlp(slots[:, :, None, :] + self.position)
        alpha = out[..., -1].softmax(dim=1)
        return (alpha[..., None] * out[..., :-1]).sum(dim=1), alpha


class SlotOutput(NamedTuple):
    slots: torch.Tensor
    attention: torch.Tensor
    features: torch.Tensor
    features_hat: torch.Tensor
    alpha: torch.Tensor
    reconstruction: torch.Tensor
    binding: torch.Tensor | None = None
    """The mask's binding term (:meth:`SlotAttention.bind`) when masks were given."""


class SlotModel(nn.Module):
    """Frames ``[B, H, W, 3]`` (uint8) -> K slots, their masks and the reconstruction of eq. 7.1."""

    def __init__(self, config: SlotConfig, frame_size: int) -> None:
        super().__init__()
        self.config, self.frame_size, self.grid = config, frame_size, frame_size // FEATURE_STRIDE
        d_e = config.feature_dim
        self.autoencoder = FrameAutoencoder(d_e)
        self.position = nn.Linear(4, d_e)
        self.token_mlp = nn.Sequential(nn.LayerNorm(d_e), nn.Linear(d_e, d_e), nn.ReLU(), nn.Linear(d_e, d_e))
        self.slot_attention = SlotAttention(d_e, config)
        self.slot_decoder = SlotDecoder(self.grid * self.grid, d_e, config)
        axis = torch.linspace(0.0, 1.0, self.grid)
        y, x = torch.meshgrid(axis, axis, indexing="ij")
        self.register_buffer("grid_coords", torch.stack([x, y, 1 - x, 1 - y], -1).view(-1, 4), persistent=False)

    def slot_parameters(self) -> list[nn.Parameter]:
        """What eq. 7.1 trains: everything but the (frozen) frame autoencoder."""
        return [p for name, p in self.named_parameters() if not name.startswith("autoencoder.")]

    def features(self, images: torch.Tensor) -> torch.Tensor:
        """e: the frozen encoder's tokens ``[B, n, d_e]`` of images ``[B, 3, H, W]``."""
        with torch.no_grad():
            return self.autoencoder.encoder(images).flatten(2).transpose(1, 2)

    def _tokens(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.features(frames_to_tensor(frames))
        return features, self.token_mlp(features + self.position(self.grid_coords))

    @torch.no_grad()
    def match_segments(self, frames: torch.Tensor, allowed: torch.Tensor,
                       tokens: torch.Tensor | None = None) -> torch.Tensor:
        """``allowed`` [B, K, n] (row s: segment s's tokens) with its rows reordered per frame so that
        each segment goes to the slot that, without masks, puts most of its attention on it (Hungarian
        matching of slots to segments): the mask prior's grouping without a slot order of its own.
        ``tokens``: the frames' tokens where the caller has them (the trainer's update), else computed."""
        tokens = self._tokens(frames)[1] if tokens is None else tokens.detach()
        _, attention = self.slot_attention(tokens)  # [B, K, n], over slots
        share = attention @ allowed.float().transpose(1, 2) / allowed.sum(-1).clamp_min(1)[:, None, :]  # [B, slot, segment]
        order = torch.stack([torch.as_tensor(linear_sum_assignment(-m.numpy())[1]) for m in share.cpu()])
        return allowed.gather(1, order.to(allowed.device)[:, :, None].expand_as(allowed))

    def forward(self, frames: torch.Tensor, allowed: torch.Tensor | None = None,
                encoded: tuple[torch.Tensor, torch.Tensor] | None = None) -> SlotOutput:
        """eq. 7.1's pass; ``encoded`` = ``(features, tokens)`` of ``frames`` where already computed."""
        features, tokens = self._tokens(frames) if encoded is None else encoded
        slots, attention, binding = self.slot_attention.bind(tokens, allowed)
        features_hat, alpha = self.slot_decoder(slots)
        grid = features_hat.transpose(1, 2).reshape(len(frames), -1, self.grid, self.grid)
        return SlotOutput(slots, attention, features, features_hat, alpha, self.autoencoder.decoder(grid),
                          None if allowed is None else binding)

    def loss(self, frames: torch.Tensor, out: SlotOutput) -> tuple[torch.Tensor, dict[str, float]]:
        """eq. 7.1: feature reconstruction plus image reconstruction (mean squared errors); plus, where
        masks were given, ``config.mask_binding`` times the binding term (``mask_binding_ce``)."""
        feature = F.mse_loss(out.features_hat, out.features)
        image = F.mse_loss(out.reconstruction, frames_to_tensor(frames))
        loss, terms = feature + image, {"feature_mse": float(feature.detach()), "image_mse": float(image.detach())}
        if out.binding is not None:
            if self.config.mask_binding > 0:
                loss = loss + self.config.mask_binding * out.binding
            terms["mask_binding_ce"] = float(out.binding.detach())
        return loss, terms

    @torch.no_grad()
    def segment(self, frames: torch.Tensor, allowed: torch.Tensor | None = None) -> torch.Tensor:
        """Each pixel's slot (int ``[B, H, W]``): the argmax of the alpha masks, upsampled bilinearly."""
        alpha = self(frames, allowed).alpha.view(len(frames), -1, self.grid, self.grid)
        return F.interpolate(alpha, size=self.frame_size, mode="bilinear", align_corners=False).argmax(dim=1)


class SlotTrainer:
    """Trains slot attention and the slot decoder on eq. 7.1 with the mask prior of ``config.mask_prior``
    over ``total_updates`` updates (the frame autoencoder is trained before, by :func:`fit_autoencoder`)."""

    def __init__(self, model: SlotModel, total_updates: int, seed: int = 0) -> None:
        self.model, self.config, self.total_updates = model, model.config, total_updates
        self.optimizer = torch.optim.Adam(model.slot_parameters(), lr=self.config.lr)
        self.generator = torch.Generator().manual_seed(seed)
        self.updates = 0

    def masks_for(self, labels: torch.Tensor, frames: torch.Tensor | None = None,
                  tokens: torch.Tensor | None = None) -> torch.Tensor | None:
        """This update's attention masks: each frame's own, or all-allowed where the prior is dropped
        (``frames``, and their ``tokens`` if computed, for ``mask_assignment="matched"``)."""
        if self.config.mask_prior == "none":
            return None
        allowed = token_masks(labels, self.config.num_slots, rule=self.config.token_mask)
        if self.config.mask_assignment == "matched":
            if frames is None:
                raise ValueError("mask_assignment 'matched' needs the frames")
            allowed = self.model.match_segments(frames, allowed, tokens)
        if self.config.mask_prior == "always":
            return allowed
        dropped = torch.rand(len(labels), generator=self.generator) < drop_probability(self.updates, self.total_updates)
        return allowed | dropped[:, None, None]

    def update(self, frames: torch.Tensor, labels: torch.Tensor) -> dict[str, float]:
        """One Adam step on eq. 7.1 for a batch of frames ``[B, H, W, 3]`` and their label maps ``[B, H, W]``."""
        self.model.train()
        encoded = self.model._tokens(frames)  # once: the matching (if any) and the pass share it
        allowed = self.masks_for(labels, frames, encoded[1])
        loss, terms = self.model.loss(frames, self.model(frames, allowed, encoded))
        self.optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.model.slot_parameters(), 1.0)
        self.optimizer.step()
        self.updates += 1
        return {"loss": float(loss.detach()), **terms, "drop_probability": drop_probability(self.updates, self.total_updates)}


def fit_autoencoder(autoencoder: nn.Module, frames: torch.Tensor, updates: int, batch_size: int = 32,
                    lr: float = 1e-3, seed: int = 0) -> float:
    """Train Enc/Dec on frames (uint8 ``[N, H, W, 3]``) by reconstruction, then freeze them; the last loss.
    Any autoencoder mapping images to their reconstruction (Dyn-O's :class:`FrameAutoencoder`, FLAM's
    FSQ one)."""
    generator = torch.Generator().manual_seed(seed)
    optimizer = torch.optim.Adam(autoencoder.parameters(), lr=lr)
    loss = torch.tensor(float("nan"))
    for _ in range(updates):
        images = frames_to_tensor(frames[torch.randint(len(frames), (batch_size,), generator=generator)])
        loss = F.mse_loss(autoencoder(images), images)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    autoencoder.requires_grad_(False)
    return float(loss.detach())
