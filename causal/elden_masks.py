"""Table 5.1's learned-mask baselines (dissertation ch. 5.3.1, Fig. 5.3c-d): Input Mask and Attention Mask.

Both are ELDEN's network (:mod:`causal.elden`) with a mask ``M`` in ``[0, 1]^{d_S x (d_S + 1)}``
computed from ``(s_t, a_t)``: ``M[j, i]`` says whether input ``i`` (a state factor, or the action,
last) may be used to predict ``s^j_{t+1}``, and it is the local graph of the transition.

* **Input Mask** (Fig. 5.3c): ``M`` multiplies the features ``phi^i`` (as pCMI's fixed mask does). It
  is binary, sampled with the straight-through Gumbel-sigmoid (Jang et al. 2017: the two-class
  Gumbel-softmax, hard in the forward pass, the relaxed sample's gradient in the backward pass), and
  regularised by the L1 norm of its open entries. The graph is the probability of each entry being open.
* **Attention Mask** (Fig. 5.3d): ``M`` modulates the attention scores (every self-attention layer
  and the output attention), as the stochastic kernel-modulated dot-product attention (SKMDPA) of
  Weiss et al. (2022) does: ``M[j, i] = exp(-(1 - cos(sigma_j, tau_i)) / h)``, a kernel between a
  learned signature ``sigma_j`` per output and a type ``tau_i`` per input computed from ``(s_t, a_t)``,
  set to 0 beyond a cosine distance ``truncation`` (straight-through), and during training sampled as
  a relaxed Bernoulli with that probability. The sparsity comes from the kernel's truncation: an
  input's type lies at one place on the sphere and reaches only the signatures near it. The graph
  is the (unsampled) kernel.

Chapter 5 trains one network per output factor ("d_S such networks"); ELDEN here shares a trunk
between a member's outputs (docs/deviations.md). A per-output mask on the inputs of a shared trunk
would not bound what output ``j`` reads (the self-attention mixes every token), so these baselines run
the trunk once per output, ``d_S`` masked copies batched together (the chapter's ``d_S`` networks, with
shared weights): in copy ``j`` input ``i`` is zeroed (Input Mask) or unread by every attention (Attention
Mask) when ``M[j, i] = 0``, so ``s^i_t`` cannot reach the prediction of ``s^j_{t+1}`` (its own token ``j``
is the output attention's query, so ``s^j_t`` always can).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from causal.elden import (ELDENConfig, ELDENModel, _attention, _linear, _norm, _stacked, interaction_layer,
                          output_heads, token_features)
from causal.elden_trainer import ELDENTrainer
from causal.factored import FactorLayout
from proto.settings import doc

MASK_KINDS = ("input", "attention")


@dataclass(frozen=True)
class MaskConfig:
    """A learned-mask baseline of Table 5.1 on ELDEN's network (the chapter gives no values for these
    settings; ours are in docs/deviations.md)."""

    kind: str = doc("input", "where the mask acts: on the input features (Input Mask) or on the attention "
                             "scores (Attention Mask)", choices=MASK_KINDS)
    mask_hidden: int = doc(64, "hidden width of the (two-layer) MLP that computes the mask from (s_t, a_t)")
    sparsity: float = doc(1e-2, "Input Mask: weight of the L1 norm of the mask (the expected number of open "
                                "entries, per transition and member) in the loss")
    init_logit: float = doc(2.0, "Input Mask: initial logit of every entry (entries start open: p = 0.88)")
    temperature: float = doc(1.0, "temperature of the Gumbel-sigmoid (Input Mask) and of the relaxed Bernoulli "
                                  "sample of the kernel (Attention Mask)")
    signature_dim: int = doc(8, "Attention Mask: size of the signatures (per output) and types (per input)")
    truncation: float = doc(1.0, "Attention Mask: kernel entries at a cosine distance above this are 0")
    bandwidth: float = doc(1.0, "Attention Mask: initial kernel bandwidth h (learned)")

    def __post_init__(self) -> None:
        if self.kind not in MASK_KINDS:
            raise ValueError(f"kind must be one of {MASK_KINDS}, got {self.kind!r}")
        if self.mask_hidden < 1 or self.signature_dim < 1:
            raise ValueError("mask_hidden and signature_dim must be >= 1")
        for name in ("temperature", "bandwidth", "truncation"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a positive finite number, got {getattr(self, name)}")
        if not (math.isfinite(self.sparsity) and self.sparsity >= 0):
            raise ValueError(f"sparsity must be a finite number >= 0, got {self.sparsity}")


class MaskedELDENModel(ELDENModel):
    """ELDEN's ensemble (the same trunk and heads, stacked over members) with a mask network per member."""

    def __init__(self, layout: FactorLayout, cfg: ELDENConfig, mask: MaskConfig) -> None:
        super().__init__(layout, cfg)
        self.mask_cfg = mask
        m, t, j, h = cfg.members, self.num_inputs, self.num_outputs, mask.mask_hidden
        flat = t * self.width
        self.mask_w1, self.mask_b1 = _stacked(m, flat, h, fan_in=flat), nn.Parameter(torch.zeros(m, h))
        self.mask_w2, self.mask_b2 = _stacked(m, h, h, fan_in=h), nn.Parameter(torch.zeros(m, h))
        if mask.kind == "input":
            self.mask_w3 = nn.Parameter(torch.zeros(m, h, j * t))
            self.mask_b3 = nn.Parameter(torch.full((m, j * t), mask.init_logit))
        else:
            c = mask.signature_dim
            self.mask_w3, self.mask_b3 = _stacked(m, h, t * c, fan_in=h), _stacked(m, t * c, fan_in=h)
            self.signatures = nn.Parameter(torch.randn(m, j, c))
            self.log_bandwidth = nn.Parameter(torch.full((m,), math.log(mask.bandwidth)))

    def _mask_hidden(self, p: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        h = torch.relu(_linear(x.flatten(2), p["mask_w1"], p["mask_b1"]))
        return _linear(torch.relu(_linear(h, p["mask_w2"], p["mask_b2"])), p["mask_w3"], p["mask_b3"])

    def mask_logits(self, p: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """Input Mask: the logit of each entry being open, ``[M, B, d_S, d_S + 1]``."""
        return self._mask_hidden(p, x).unflatten(-1, (self.num_outputs, self.num_inputs))

    def kernel(self, p: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """Attention Mask: the truncated kernel ``[M, B, d_S, d_S + 1]`` between each output's signature
        and each input's type (computed from the whole ``(s_t, a_t)``); 0 beyond the truncation in the
        forward pass, the untruncated kernel's gradient in the backward pass (straight-through)."""
        types = F.normalize(self._mask_hidden(p, x).unflatten(-1, (self.num_inputs, -1)), dim=-1)
        signatures = F.normalize(p["signatures"], dim=-1)
        distance = 1.0 - torch.einsum("mjc,mbtc->mbjt", signatures, types)
        full = torch.exp(-distance / p["log_bandwidth"].exp().view(-1, 1, 1, 1))
        truncated = full * (distance <= self.mask_cfg.truncation)
        return full + (truncated - full).detach()

    def mask_scores(self, p: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """The mask's value without sampling, ``[M, B, d_S, d_S + 1]`` in [0, 1]: each entry's probability
        of being open (Input Mask) or the kernel (Attention Mask). The local graph."""
        if self.mask_cfg.kind == "input":
            return torch.sigmoid(self.mask_logits(p, x))
        return self.kernel(p, x)

    def sample_mask(self, p: dict[str, torch.Tensor], x: torch.Tensor,
                    generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """A training mask and the scores it was drawn from: a straight-through Gumbel-sigmoid sample
        (binary forward) of the Input Mask, or a relaxed Bernoulli sample of the kernel."""
        tau = self.mask_cfg.temperature
        u = torch.rand(x.shape[0], x.shape[1], self.num_outputs, self.num_inputs, generator=generator)
        noise = torch.log(u.clamp(1e-6, 1 - 1e-6)) - torch.log1p(-u.clamp(1e-6, 1 - 1e-6))
        if self.mask_cfg.kind == "input":
            logits = self.mask_logits(p, x)
            soft = torch.sigmoid((logits + noise) / tau)
            return soft + ((soft > 0.5).float() - soft).detach(), torch.sigmoid(logits)
        scores = self.kernel(p, x)
        probs = scores.clamp(1e-6, 1 - 1e-6)
        return torch.sigmoid((torch.log(probs) - torch.log1p(-probs) + noise) / tau) * (scores > 0), scores

    def masked_raw(self, p: dict[str, torch.Tensor], x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Raw outputs ``[M, B, d_S, O]`` of every member on its inputs ``x`` [M, B, T, W] under ``mask``
        [M, B, d_S, T]: the trunk runs once per output ``j`` (copies batched with the samples), copy ``j``
        masked by row ``M[j]``, and output ``j`` reads copy ``j`` with its own token as the query."""
        m, b, j, t = mask.shape
        d = p["token_b2"].shape[-1]
        phi = token_features(p, x)[:, :, None].expand(m, b, j, t, d)
        rows = mask.reshape(m, b * j, t)
        modulation = None
        if self.mask_cfg.kind == "input":
            theta = (phi * mask[..., None]).reshape(m, b * j, t, d)
        else:
            theta = phi.reshape(m, b * j, t, d)
            modulation = rows[:, :, None, None, :]  # [M, B d_S, heads, queries, keys]
        for layer in range(p["ln1_g"].shape[1]):
            theta = interaction_layer(p, layer, theta, self.cfg.heads, modulation)[0]
        z = _norm(theta, p["lno_g"], p["lno_b"])
        own = torch.arange(j)
        query = z.view(m, b, j, t, d)[:, :, own, own].reshape(m, b * j, 1, d)
        read = _attention(p, "out", query, z, self.cfg.heads, modulation)[0]
        return output_heads(p, read.view(m, b, j, d))

    def raw(self, params: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """Raw outputs under the unsampled mask: entries open where their probability is at least 0.5
        (Input Mask), or modulated by the kernel (Attention Mask)."""
        scores = self.mask_scores(params, x)
        return self.masked_raw(params, x, (scores >= 0.5).float() if self.mask_cfg.kind == "input" else scores)


@torch.no_grad()
def mask_graphs(model: MaskedELDENModel, state: torch.Tensor, action: torch.Tensor, chunk: int = 512) -> torch.Tensor:
    """The baseline's local graphs: the mask's scores averaged over members, ``[B, d_S, d_S + 1]``."""
    params = model.params()
    parts = [model.mask_scores(params, model.per_member(model.encode(state[k : k + chunk], action[k : k + chunk])))
             .mean(dim=0) for k in range(0, state.shape[0], chunk)]
    return torch.cat(parts) if parts else torch.zeros(0, model.num_outputs, model.num_inputs)


class MaskTrainer(ELDENTrainer):
    """Trains a :class:`MaskedELDENModel` as the dynamics-learner trains ELDEN (``members x
    member_batch`` rows, member ``k`` on its own share, Adam, the same clip): the NLL of every factor
    under a sampled mask, plus (Input Mask) ``sparsity`` x the L1 norm of the mask. Neither ELDEN's
    gradient regulariser nor its Mixup (which makes derivatives of discrete inputs meaningful; these
    graphs are no derivatives) is used."""

    def __init__(self, layout: FactorLayout, cfg: ELDENConfig, mask: MaskConfig, seed: int = 0) -> None:
        self.mask_cfg = mask
        super().__init__(layout, cfg, seed=seed)
        self.uses_mixup = False
        self.generator = torch.Generator().manual_seed(seed)

    def build_model(self, layout: FactorLayout, cfg: ELDENConfig) -> MaskedELDENModel:
        return MaskedELDENModel(layout, cfg, self.mask_cfg)

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        """One Adam step; returns the mean NLL per factor, the mean mask score and (Input Mask) the L1 term."""
        x, targets = self.split(state, action, next_state)
        params = self.model.params()
        mask, scores = self.model.sample_mask(params, x, self.generator)
        nll = -self.model.log_likelihood(self.model.masked_raw(params, x, mask), targets)
        loss = nll.mean(dim=1).sum()
        stats = {"nll_full": float(nll.detach().mean()), "mask_mean": float(scores.detach().mean())}
        if self.mask_cfg.kind == "input" and self.mask_cfg.sparsity > 0:
            l1 = scores.sum(dim=(2, 3)).mean(dim=1).sum()
            loss = loss + self.mask_cfg.sparsity * l1
            stats["mask_l1"] = float(l1.detach()) / self.cfg.members
        return self.step(loss, stats)

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "mask_rng": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.generator.set_state(state["mask_rng"])
