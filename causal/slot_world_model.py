"""Dyn-O's world model over slots (dissertation section 7.2.2, eq. 7.2) and its monolithic baseline.

    u_t^k = Self-Attn(query = xi_t^k, key = [xi_t^1, ..., xi_t^K, a_t])
    h_{t+1}^k = Core(h_t^k, u_t^k),   xi^_{t+1}^k = xi_t^k + Pred(h_{t+1}^k)
    r^_t = Cross-Attn(r_cls, [h_{t+1}^1..K]),   tau^_t = Cross-Attn(tau_cls, [h_{t+1}^1..K])
    L_wm = sum_t ||xi^_{t+1} - xi_{t+1}||^2 + sum_t (||r^_t - r_t||^2 + CE(tau^_t, tau_t))      (eq. 7.2)

- ``Core`` is a GRU cell shared across slots, where the chapter has a Mamba state-space model (a
  deviation, docs/deviations.md): both carry a per-slot hidden state through time, and one cell
  applied to every slot keeps the model permutation-equivariant, as no position encoding is used.
- ``Pred`` predicts the change of the slot (a residual), which the chapter leaves open.
- :class:`MonolithicWorldModel` is the baseline of Table 7.2's analogue: one latent per frame (the
  frozen encoder's whole feature map, flattened), a GRU over it and the action, of a width chosen so
  its parameter count matches the slot model's (:func:`monolithic_width`).
- :func:`align_slots` puts the slots of a sequence in one order over time (slot attention's order is
  free in each frame), by matching each frame's slot masks to the previous frame's.
- :func:`psnr` and :func:`ssim` score decoded rollouts (images in [0, 1]).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from torch import nn

from proto.settings import doc


@dataclass(frozen=True)
class WorldModelConfig:
    """Sizes and optimiser of eq. 7.2's world model."""

    hidden: int = doc(64, "per-slot hidden state of the recurrent core (shared across slots)")
    heads: int = doc(4, "attention heads of the slot self-attention and the reward/termination read-out")
    lr: float = doc(1e-3, "Adam learning rate of the world model")

    def __post_init__(self) -> None:
        if min(self.hidden, self.heads) < 1 or not self.lr > 0:
            raise ValueError("world-model hidden size, heads and lr must be positive")


class WorldStep(NamedTuple):
    next_slots: torch.Tensor
    reward: torch.Tensor
    termination_logit: torch.Tensor
    hidden: torch.Tensor


class SlotWorldModel(nn.Module):
    """eq. 7.2 over slots ``[B, K, d_xi]`` and discrete actions ``[B]``; equivariant to slot permutations."""

    def __init__(self, slot_dim: int, action_size: int, config: WorldModelConfig) -> None:
        super().__init__()
        h = config.hidden
        self.hidden_size = h
        self.action_embed = nn.Embedding(action_size, slot_dim)
        self.norm_query, self.norm_key = nn.LayerNorm(slot_dim), nn.LayerNorm(slot_dim)
        self.self_attention = nn.MultiheadAttention(slot_dim, _heads(slot_dim, config.heads), batch_first=True)
        self.core = nn.GRUCell(slot_dim, h)
        self.predict = nn.Sequential(nn.Linear(h, h), nn.ReLU(), nn.Linear(h, slot_dim))
        self.queries = nn.Parameter(torch.randn(2, h) * h ** -0.5)
        self.read_out = nn.MultiheadAttention(h, _heads(h, config.heads), batch_first=True)
        self.heads = nn.Linear(h, 1)

    def initial_hidden(self, slots: torch.Tensor) -> torch.Tensor:
        return slots.new_zeros(slots.shape[:-1] + (self.hidden_size,))

    def step(self, slots: torch.Tensor, action: torch.Tensor, hidden: torch.Tensor) -> WorldStep:
        """One step: next slots ``[B, K, d]``, reward ``[B]``, termination logit ``[B]``, hidden ``[B, K, h]``."""
        keys = self.norm_key(torch.cat([slots, self.action_embed(action)[:, None]], dim=1))
        attended, _ = self.self_attention(self.norm_query(slots), keys, keys, need_weights=False)
        u = slots + attended
        hidden = self.core(u.flatten(0, 1), hidden.flatten(0, 1)).view_as(hidden)
        queries = self.queries.expand(len(slots), -1, -1)
        read, _ = self.read_out(queries, hidden, hidden, need_weights=False)
        out = self.heads(read)[..., 0]
        return WorldStep(slots + self.predict(hidden), out[:, 0], out[:, 1], hidden)

    def forward(self, slots: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Teacher-forced predictions over a sequence: slots ``[B, T, K, d]``, actions ``[B, T]`` ->
        predicted next slots ``[B, T, K, d]`` (entry t predicts t + 1), rewards and termination logits ``[B, T]``."""
        hidden = self.initial_hidden(slots[:, 0])
        outs = []
        for t in range(slots.shape[1]):
            step = self.step(slots[:, t], actions[:, t], hidden)
            hidden = step.hidden
            outs.append(step)
        return (torch.stack([o.next_slots for o in outs], 1), torch.stack([o.reward for o in outs], 1),
                torch.stack([o.termination_logit for o in outs], 1))

    @torch.no_grad()
    def observe(self, slots: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The hidden state ``[B, K, h]`` after reading context frames' slots ``[B, C, K, d]`` and the
        actions taken from them ``[B, C]`` (teacher-forced, as in :meth:`forward`): the state from which
        :meth:`rollout` continues at frame ``C``."""
        hidden = self.initial_hidden(slots[:, 0])
        for t in range(slots.shape[1]):
            hidden = self.step(slots[:, t], actions[:, t], hidden).hidden
        return hidden

    @torch.no_grad()
    def rollout(self, slots: torch.Tensor, actions: torch.Tensor, hidden: torch.Tensor | None = None) -> torch.Tensor:
        """Open loop from slots ``[B, K, d]`` under actions ``[B, H]``: predicted slots ``[B, H, K, d]``;
        ``hidden`` from :meth:`observe` to continue after context frames (default: none seen)."""
        hidden, out = self.initial_hidden(slots) if hidden is None else hidden, []
        for t in range(actions.shape[1]):
            step = self.step(slots, actions[:, t], hidden)
            slots, hidden = step.next_slots, step.hidden
            out.append(slots)
        return torch.stack(out, 1)


class MonolithicWorldModel(nn.Module):
    """The baseline: one latent per frame (``latent_dim`` values) -> a GRU with the action -> the next latent."""

    def __init__(self, latent_dim: int, action_size: int, width: int) -> None:
        super().__init__()
        self.width = width
        self.encode = nn.Linear(latent_dim, width)
        self.action_embed = nn.Embedding(action_size, width)
        self.core = nn.GRUCell(2 * width, width)
        self.predict = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Linear(width, latent_dim))
        self.heads = nn.Linear(width, 2)

    def step(self, latent: torch.Tensor, action: torch.Tensor, hidden: torch.Tensor) -> WorldStep:
        hidden = self.core(torch.cat([self.encode(latent), self.action_embed(action)], dim=1), hidden)
        out = self.heads(hidden)
        return WorldStep(latent + self.predict(hidden), out[:, 0], out[:, 1], hidden)

    def forward(self, latents: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Teacher-forced: latents ``[B, T, D]``, actions ``[B, T]`` -> next latents, rewards, termination logits."""
        hidden, outs = latents.new_zeros(len(latents), self.width), []
        for t in range(latents.shape[1]):
            step = self.step(latents[:, t], actions[:, t], hidden)
            hidden = step.hidden
            outs.append(step)
        return (torch.stack([o.next_slots for o in outs], 1), torch.stack([o.reward for o in outs], 1),
                torch.stack([o.termination_logit for o in outs], 1))

    @torch.no_grad()
    def observe(self, latents: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The hidden state ``[B, width]`` after context latents ``[B, C, D]`` and actions ``[B, C]``."""
        hidden = latents.new_zeros(len(latents), self.width)
        for t in range(latents.shape[1]):
            hidden = self.step(latents[:, t], actions[:, t], hidden).hidden
        return hidden

    @torch.no_grad()
    def rollout(self, latent: torch.Tensor, actions: torch.Tensor, hidden: torch.Tensor | None = None) -> torch.Tensor:
        """Open loop from latents ``[B, D]``: predicted latents ``[B, H, D]``; ``hidden`` from
        :meth:`observe` to continue after context frames."""
        hidden, out = latent.new_zeros(len(latent), self.width) if hidden is None else hidden, []
        for t in range(actions.shape[1]):
            step = self.step(latent, actions[:, t], hidden)
            latent, hidden = step.next_slots, step.hidden
            out.append(latent)
        return torch.stack(out, 1)


def world_model_loss(predicted: tuple[torch.Tensor, torch.Tensor, torch.Tensor], next_latents: torch.Tensor,
                     rewards: torch.Tensor | None = None, terminations: torch.Tensor | None = None) -> torch.Tensor:
    """eq. 7.2 (means instead of sums): next-latent error, plus the reward's squared error and the
    termination's cross-entropy where the environment gives them."""
    latents, reward, termination = predicted
    loss = F.mse_loss(latents, next_latents)
    if rewards is not None:
        loss = loss + F.mse_loss(reward, rewards)
    if terminations is not None:
        loss = loss + F.binary_cross_entropy_with_logits(termination, terminations.float())
    return loss


def parameter_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def monolithic_width(latent_dim: int, action_size: int, target: int) -> int:
    """The width whose :class:`MonolithicWorldModel` has the parameter count nearest ``target``."""
    def count(w: int) -> int:
        return parameter_count(MonolithicWorldModel(latent_dim, action_size, w))
    low, high = 1, 4096
    while low < high:  # the smallest width reaching the target (the count grows with the width)
        mid = (low + high) // 2
        low, high = (mid + 1, high) if count(mid) < target else (low, mid)
    return min((max(low - 1, 1), low), key=lambda w: abs(count(w) - target))


def align_slots(slots: torch.Tensor, masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Slots ``[B, T, K, d]`` and their masks ``[B, T, K, n]`` with frame t's slots reordered to match
    frame t - 1's (a maximum-overlap assignment of the masks), so slot k is one object over the sequence."""
    slots, masks = slots.clone(), masks.clone()
    for b in range(slots.shape[0]):
        for t in range(1, slots.shape[1]):
            overlap = (masks[b, t - 1] @ masks[b, t].T).numpy()
            _, order = linear_sum_assignment(-overlap)
            slots[b, t], masks[b, t] = slots[b, t, order], masks[b, t, order]
    return slots, masks


def psnr(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image ``[..., C, H, W]`` (values in [0, 1]); the squared
    error is floored at 1e-10, so identical images score 100 dB rather than infinity."""
    mse = (predicted.clamp(0, 1) - target).square().flatten(-3).mean(-1).clamp_min(1e-10)
    return 10.0 * torch.log10(1.0 / mse)


def ssim(predicted: torch.Tensor, target: torch.Tensor, window: int = 7, sigma: float = 1.5) -> torch.Tensor:
    """Structural similarity per image ``[B, C, H, W]`` (values in [0, 1]): the mean over pixels and
    channels of SSIM's map with a Gaussian window (Wang et al. 2004; C1 = 0.01^2, C2 = 0.03^2),
    ``window`` x ``window`` and valid positions only."""
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    x, y = predicted.clamp(0, 1).double(), target.double()
    channels = x.shape[1]
    axis = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    g = torch.exp(-axis.square() / (2 * sigma ** 2))
    g = g / g.sum()
    kernel = (g[:, None] * g[None, :]).expand(channels, 1, window, window)

    def blur(image: torch.Tensor) -> torch.Tensor:
        return F.conv2d(image, kernel, groups=channels)

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    index = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return index.flatten(1).mean(1).float()


def _heads(dim: int, wanted: int) -> int:
    """The most heads up to ``wanted`` that divide ``dim`` (multi-head attention needs it)."""
    return max(h for h in range(1, wanted + 1) if dim % h == 0)


def summary_of(values: list[float]) -> dict[str, float]:
    """Mean and standard error of per-rollout scores (Table 7.2 reports mean and standard error)."""
    array = np.asarray(values, dtype=float)
    return {"mean": float(array.mean()), "stderr": float(array.std(ddof=1) / np.sqrt(len(array))) if len(array) > 1 else 0.0}
