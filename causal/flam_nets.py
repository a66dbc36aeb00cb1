"""FLAM's networks (dissertation section 8.2): the FSQ autoencoder, the factorizer, the per-slot inverse
and forward dynamics and the aggregator. Every network is vectorised over slots (the slot axis is a
batch axis); :mod:`causal.flam` puts them together with the loss of eq. 8.6.

Shapes: ``B`` clips of ``T`` frames, ``n`` feature tokens of ``d_e`` channels, ``K`` slots of ``D``
channels, latent actions of ``d_a`` channels per slot.
"""
from __future__ import annotations

import torch
from torch import nn

from causal.slots import FrameAutoencoder, balanced_binding, restrict_attention


class FSQ(nn.Module):
    """Finite scalar quantisation (Mentzer et al. 2024): channel ``c`` is bounded to ``L_c`` levels by
    ``tanh`` and rounded with a straight-through gradient; values are scaled to ``[-1, 1]``."""

    def __init__(self, levels: tuple[int, ...]) -> None:
        super().__init__()
        if not levels or any(level < 2 or level % 2 == 0 for level in levels):
            raise ValueError(f"FSQ levels must be odd and >= 3, got {levels}")
        self.levels = levels
        self.register_buffer("half_width", (torch.tensor(levels, dtype=torch.float32) - 1) / 2, persistent=False)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """Quantised ``z`` (channels last): ``round(tanh(z) * h) / h`` with ``h = (L - 1) / 2``."""
        bounded = torch.tanh(z) * self.half_width
        return (bounded + (torch.round(bounded) - bounded).detach()) / self.half_width

    def snap(self, values: torch.Tensor) -> torch.Tensor:
        """The grid point nearest to ``values`` already in ``[-1, 1]`` (a prediction fed back in a rollout)."""
        return torch.round(values.clamp(-1.0, 1.0) * self.half_width) / self.half_width


class FSQAutoencoder(nn.Module):
    """Encoder, FSQ and decoder of eq. 8.1: images ``[B, 3, H, W]`` <-> tokens ``e_q [B, n, d_e]``.

    The convolutional stacks are Dyn-O's :class:`causal.slots.FrameAutoencoder` (stride 4)."""

    def __init__(self, levels: tuple[int, ...], width: int = 32) -> None:
        super().__init__()
        self.fsq = FSQ(levels)
        self.autoencoder = FrameAutoencoder(len(levels), width)

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        z = self.autoencoder.encoder(images)
        return self.fsq(z.flatten(2).transpose(1, 2))

    def decode(self, tokens: torch.Tensor, grid: int) -> torch.Tensor:
        return self.autoencoder.decoder(tokens.transpose(1, 2).reshape(len(tokens), -1, grid, grid))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(images), images.shape[-1] // 4)


class AttentionBlock(nn.Module):
    """Pre-norm attention from ``query [M, q, D]`` to ``key [M, k, D]`` with residual, then an MLP."""

    def __init__(self, dim: int, heads: int = 4) -> None:
        super().__init__()
        self.norm_query, self.norm_key = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.attention = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.mlp = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 2 * dim), nn.ReLU(), nn.Linear(2 * dim, dim))

    def forward(self, query: torch.Tensor, key: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        k = self.norm_key(key)
        x = query + self.attention(self.norm_query(query), k, k, attn_mask=mask, need_weights=False)[0]
        return x + self.mlp(x)


def grid_fourier_features(num_tokens: int) -> torch.Tensor:
    """``[n, 4 g / 2]``: sin and cos of pi k x and pi k y (k = 1..g/2) of a square grid's token centres."""
    grid = int(round(num_tokens ** 0.5))
    if grid * grid != num_tokens:
        raise ValueError(f"tokens must form a square grid, got {num_tokens}")
    axis = (torch.arange(grid, dtype=torch.float32) + 0.5) / grid
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    angles = torch.pi * torch.arange(1, max(grid // 2, 1) + 1, dtype=torch.float32)
    coords = torch.stack([x.reshape(-1), y.reshape(-1)], -1)[:, :, None] * angles
    return torch.cat([coords.sin(), coords.cos()], -1).flatten(1)


class TokenEmbedding(nn.Module):
    """Feature tokens ``[..., n, d_e]`` -> ``[..., n, D]`` plus a position embedding: a learned projection
    of fixed Fourier features of the token's grid cell (distinct positions from the first update on)."""

    def __init__(self, feature_dim: int, num_tokens: int, dim: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(feature_dim, dim), nn.ReLU(), nn.Linear(dim, dim))
        self.register_buffer("fourier", grid_fourier_features(num_tokens), persistent=False)
        self.position = nn.Linear(self.fourier.shape[1], dim)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.mlp(features) + self.position(self.fourier)


class Factorizer(nn.Module):
    """Eqs. 8.2-8.3: slot attention over each frame's tokens from K learned initial slots, each
    iteration followed by causal temporal self-attention of every slot over its own past values.

    ``temporal=False`` is Table 8.5's ablation "w/o temporal attention": as in SAVi, the frames are
    taken in order and each frame's slot attention starts from the previous frame's slots (the first
    frame's from the learned initial slots), with no temporal attention."""

    def __init__(self, feature_dim: int, num_tokens: int, num_slots: int, dim: int, iterations: int,
                 temporal: bool = True) -> None:
        super().__init__()
        self.iterations, self.scale = iterations, dim ** -0.5
        self.embed = TokenEmbedding(feature_dim, num_tokens, dim)
        self.initial = nn.Parameter(torch.randn(num_slots, dim) * dim ** -0.5)
        self.norm_tokens, self.norm_slots = nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.to_q, self.to_k, self.to_v = (nn.Linear(dim, dim, bias=False) for _ in range(3))
        self.gru = nn.GRUCell(dim, dim)
        self.mlp = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 2 * dim), nn.ReLU(), nn.Linear(2 * dim, dim))
        self.temporal = AttentionBlock(dim) if temporal else None

    def _attend(self, slots: torch.Tensor, keys: torch.Tensor, values: torch.Tensor,
                allowed: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One slot-attention iteration on ``M`` frames: slots ``[M, K, D]``, keys and values
        ``[M, n, D]``, ``allowed`` ``[M, K, n]`` or None -> (slots, attention ``[M, K, n]``, each
        token's binding cross-entropy ``[M, n]``: :func:`causal.slots.restrict_attention`)."""
        m, k, d = slots.shape
        logits = torch.einsum("mkd,mnd->mkn", self.to_q(self.norm_slots(slots)), keys) * self.scale
        logits, binding = restrict_attention(logits, allowed)
        attention = logits.softmax(dim=1)
        updates = (attention / (attention.sum(dim=2, keepdim=True) + 1e-8)) @ values
        slots = self.gru(updates.reshape(-1, d), slots.reshape(-1, d)).view(m, k, d)
        return slots + self.mlp(slots), attention, binding

    def forward(self, features: torch.Tensor, allowed: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Slots ``[B, T, K, D]`` of features ``[B, T, n, d_e]`` and the last slot attention
        ``[B, T, K, n]`` (normalised over slots: each token's share per slot). ``allowed`` (bool
        ``[B, T, K, n]``) is Dyn-O's mask prior: slot ``k`` attends only to its tokens."""
        slots, attention, _ = self.bind(features, allowed)
        return slots, attention

    def bind(self, features: torch.Tensor, allowed: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`forward`'s slots and attention, and the mask's binding term: the cross-entropy of the
        attention computed without the mask against the slots the mask allows, averaged over the
        iterations, then per segment and over the segments of the frames whose mask is not dropped
        (:func:`causal.slots.balanced_binding`). It is 0 when the slots would bind as the mask binds
        them without it; :class:`causal.flam.LAMTrainer` weights it by ``FLAMConfig.mask_binding``."""
        b, t, n, _ = features.shape
        tokens = self.norm_tokens(self.embed(features)).flatten(0, 1)
        keys, values = self.to_k(tokens), self.to_v(tokens)
        k, d = self.initial.shape
        if self.temporal is None:
            return self._sequential(keys.view(b, t, n, d), values.view(b, t, n, d), allowed)
        slots = self.initial.expand(b * t, k, d)
        causal = torch.ones(t, t, dtype=torch.bool).triu(1)
        frame_allowed = None if allowed is None else allowed.flatten(0, 1)
        binding = keys.new_zeros(b * t, n)
        for _ in range(self.iterations):
            slots, attention, token_binding = self._attend(slots, keys, values, frame_allowed)
            binding = binding + token_binding / self.iterations
            per_slot = slots.view(b, t, k, d).transpose(1, 2).reshape(b * k, t, d)
            per_slot = self.temporal(per_slot, per_slot, causal)
            slots = per_slot.view(b, k, t, d).transpose(1, 2).reshape(b * t, k, d)
        return slots.view(b, t, k, d), attention.view(b, t, k, n), balanced_binding(binding, frame_allowed)

    def _sequential(self, keys: torch.Tensor, values: torch.Tensor, allowed: torch.Tensor | None
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SAVi-style slots (no temporal attention): frame by frame, each initialised from the last."""
        b, t = keys.shape[:2]
        k, d = self.initial.shape
        slots = self.initial.expand(b, k, d)
        all_slots, all_attention, all_binding = [], [], []
        for step in range(t):
            binding = keys.new_zeros(b, keys.shape[2])
            for _ in range(self.iterations):
                slots, attention, token_binding = self._attend(slots, keys[:, step], values[:, step],
                                                               None if allowed is None else allowed[:, step])
                binding = binding + token_binding / self.iterations
            all_slots.append(slots)
            all_attention.append(attention)
            all_binding.append(binding)
        frame_allowed = None if allowed is None else allowed.flatten(0, 1)
        return (torch.stack(all_slots, dim=1), torch.stack(all_attention, dim=1),
                balanced_binding(torch.stack(all_binding, dim=1).flatten(0, 1), frame_allowed))


def per_slot_cross(block: AttentionBlock, query: torch.Tensor, keys: tuple[torch.Tensor, ...],
                   coupled: bool = False) -> torch.Tensor:
    """Each slot's query ``[M, K, D]`` attends only to its own keys (each ``[M, K, D]``): ``[M, K, D]``.
    ``coupled=True`` (Table 8.5's Global-Coupled FLAM): every slot's query attends to every slot's keys."""
    if coupled:
        return block(query, torch.cat(keys, dim=1))
    m, k, d = query.shape
    return block(query.reshape(m * k, 1, d), torch.stack(keys, dim=2).reshape(m * k, len(keys), d)).view(m, k, d)


class InverseDynamics(nn.Module):
    """Eq. 8.4: alpha^i from all slots at t and slot i at t+1, as a Gaussian ``(mu, log_sigma)``.

    Spatial self-attention across the slots at t, then slot i's next value cross-attends to
    ``[its spatial summary, its next value]``; M_mu and M_sigma project to ``d_a`` channels.
    ``coupled=True`` is Table 8.5's Global-Coupled FLAM: alpha^i from all slots at t and t+1 (slot i's
    next value attends to every slot's summary and every slot's next value)."""

    def __init__(self, dim: int, action_dim: int, coupled: bool = False) -> None:
        super().__init__()
        self.spatial, self.temporal = AttentionBlock(dim), AttentionBlock(dim)
        self.to_mu, self.to_log_sigma = nn.Linear(dim, action_dim), posterior_scale(dim, action_dim)
        self.coupled = coupled

    def forward(self, current: torch.Tensor, nxt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        summary = self.spatial(current, current)
        alpha = per_slot_cross(self.temporal, nxt, (summary, nxt), self.coupled)
        return self.to_mu(alpha), self.to_log_sigma(alpha).clamp(-8.0, 4.0)


class ForwardDynamics(nn.Module):
    """Eq. 8.5: slot i's next value from all slots at t and its own latent action alpha^i only
    (``coupled=True``, Global-Coupled FLAM: from all slots at t and every slot's latent action)."""

    def __init__(self, dim: int, action_dim: int, coupled: bool = False) -> None:
        super().__init__()
        self.spatial, self.temporal = AttentionBlock(dim), AttentionBlock(dim)
        self.action_in = nn.Linear(action_dim, dim)
        self.coupled = coupled

    def forward(self, current: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        summary = self.spatial(current, current)
        return per_slot_cross(self.temporal, current, (summary, self.action_in(alpha)), self.coupled)


class Aggregator(nn.Module):
    """e^_{t+1} = e_t + Out(Cross-Attn(query = e_t, key = xi^_{t+1})): features from predicted slots."""

    def __init__(self, feature_dim: int, num_tokens: int, dim: int) -> None:
        super().__init__()
        self.embed = TokenEmbedding(feature_dim, num_tokens, dim)
        self.block = AttentionBlock(dim)
        self.out = nn.Linear(dim, feature_dim)

    def forward(self, features: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
        return features + self.out(self.block(self.embed(features), slots))


class BroadcastAggregator(nn.Module):
    """A spatial-broadcast aggregator: each predicted slot, plus the Fourier position of each token,
    goes through a per-token MLP to features and an alpha logit; the alphas (a softmax over slots)
    mix the slots' features into e^_{t+1}. The slots draw the whole next frame (no e_t)."""

    def __init__(self, feature_dim: int, num_tokens: int, dim: int) -> None:
        super().__init__()
        self.register_buffer("fourier", grid_fourier_features(num_tokens), persistent=False)
        self.position = nn.Linear(self.fourier.shape[1], dim)
        self.mlp = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU(),
                                 nn.Linear(dim, feature_dim + 1))

    def forward(self, features: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
        out = self.mlp(slots[:, :, None, :] + self.position(self.fourier))
        return (out[..., -1].softmax(dim=1)[..., None] * out[..., :-1]).sum(dim=1)


def posterior_scale(dim: int, action_dim: int, initial_log_sigma: float = -3.0) -> nn.Linear:
    """M_sigma as a log-scale head starting near ``initial_log_sigma``: a posterior that starts narrow
    keeps the latent action informative while the FDM learns to use it (at sigma = 1 the FDM first
    learns to ignore the noise, and the posterior collapses to the prior)."""
    head = nn.Linear(dim, action_dim)
    nn.init.constant_(head.bias, initial_log_sigma)
    return head


def gaussian_kl(mu: torch.Tensor, log_sigma: torch.Tensor) -> torch.Tensor:
    """KL[N(mu, sigma^2) || N(0, I)] summed over the last axis (closed form)."""
    return 0.5 * (mu.pow(2) + torch.exp(2 * log_sigma) - 1.0 - 2 * log_sigma).sum(-1)
