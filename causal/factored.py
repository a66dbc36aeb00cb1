"""Factored state spaces: how a flat state vector splits into the factors a causal model reasons about.

The flat layout is the one of ``proto.messages``: a categorical factor takes one slot (its category
index), a continuous factor ``size`` slots. Models see each factor as its own input: a one-hot for a
categorical factor, ``(x - loc) / scale`` for a continuous one, zero-padded to a common width so the
per-factor networks can run as one batched module.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from proto.messages import EnvSpec


@dataclass(frozen=True)
class FactorLayout:
    """Kinds, sizes and normalisation of the state factors and the action."""

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    sizes: tuple[int, ...]
    locs: tuple[float, ...]
    scales: tuple[float, ...]
    action_kind: str
    action_size: int

    @classmethod
    def from_spec(cls, spec: EnvSpec) -> "FactorLayout":
        return cls(
            names=tuple(spec.factor_names), kinds=tuple(spec.factor_kinds), sizes=tuple(spec.factor_sizes),
            locs=tuple(spec.factor_locs), scales=tuple(spec.factor_scales),
            action_kind=spec.action_kind, action_size=spec.action_size,
        )

    @property
    def num_factors(self) -> int:
        return len(self.kinds)

    @property
    def state_dim(self) -> int:
        return sum(self.slots(j) for j in range(self.num_factors))

    def slots(self, j: int) -> int:
        """Width of factor ``j`` in the flat state vector."""
        return 1 if self.kinds[j] == "categorical" else self.sizes[j]

    def offsets(self) -> list[int]:
        out, pos = [], 0
        for j in range(self.num_factors):
            out.append(pos)
            pos += self.slots(j)
        return out

    @property
    def input_width(self) -> int:
        """Width of one factor's encoded input (one-hot or normalised values), padded."""
        return max(self.sizes)

    @property
    def action_width(self) -> int:
        return self.action_size

    @property
    def categorical(self) -> list[int]:
        return [j for j, k in enumerate(self.kinds) if k == "categorical"]

    @property
    def continuous(self) -> list[int]:
        return [j for j, k in enumerate(self.kinds) if k == "continuous"]

    @property
    def head_width(self) -> int:
        """Output width of a predictive head: logits, or a mean and a log-std per dimension."""
        return max(s if k == "categorical" else 2 * s for k, s in zip(self.kinds, self.sizes))


class FactorCodec(torch.nn.Module):
    """Turns flat states and actions into per-factor model inputs and prediction targets."""

    def __init__(self, layout: FactorLayout) -> None:
        super().__init__()
        self.layout = layout
        offsets = layout.offsets()
        cat, cont = layout.categorical, layout.continuous
        self.cat_factors = cat
        self.cont_factors = cont
        self.max_cat = max([layout.sizes[j] for j in cat], default=1)
        self.max_cont = max([layout.sizes[j] for j in cont], default=1)
        self.register_buffer("cat_cols", torch.tensor([offsets[j] for j in cat], dtype=torch.long))
        self.register_buffer("cat_sizes", torch.tensor([layout.sizes[j] for j in cat], dtype=torch.long))
        cols, valid = self._continuous_columns(offsets)
        self.register_buffer("cont_cols", cols)
        self.register_buffer("cont_valid", valid)
        self.register_buffer("cont_loc", torch.tensor([layout.locs[j] for j in cont], dtype=torch.float32))
        self.register_buffer("cont_scale", torch.tensor([layout.scales[j] for j in cont], dtype=torch.float32))
        self.register_buffer("cat_index", torch.tensor(cat, dtype=torch.long))
        self.register_buffer("cont_index", torch.tensor(cont, dtype=torch.long))

    def _continuous_columns(self, offsets: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        cols = torch.zeros(len(self.cont_factors), self.max_cont, dtype=torch.long)
        valid = torch.zeros(len(self.cont_factors), self.max_cont, dtype=torch.bool)
        for n, j in enumerate(self.cont_factors):
            size = self.layout.sizes[j]
            cols[n, :size] = torch.arange(offsets[j], offsets[j] + size)
            valid[n, :size] = True
        return cols, valid

    def categories(self, state: torch.Tensor) -> torch.Tensor:
        """[B, n_cat] long category indices of the categorical factors."""
        return state[:, self.cat_cols].round().long().clamp_min(0)

    def continuous_values(self, state: torch.Tensor) -> torch.Tensor:
        """[B, n_cont, max_cont] normalised values of the continuous factors (zero where padded)."""
        raw = state[:, self.cont_cols]
        norm = (raw - self.cont_loc[None, :, None]) / self.cont_scale[None, :, None]
        return norm * self.cont_valid

    def encode_state(self, state: torch.Tensor) -> torch.Tensor:
        """[B, d_S, input_width] per-factor inputs."""
        batch = state.shape[0]
        width = self.layout.input_width
        out = state.new_zeros(batch, self.layout.num_factors, width)
        if self.cat_factors:
            onehot = F.one_hot(self.categories(state).clamp_max(self.max_cat - 1), self.max_cat).to(state.dtype)
            out[:, self.cat_index, : self.max_cat] = onehot
        if self.cont_factors:
            out[:, self.cont_index, : self.max_cont] = self.continuous_values(state)
        return out

    def encode_action(self, action: torch.Tensor) -> torch.Tensor:
        """[B, action_width]: one-hot for a categorical action, the raw vector otherwise."""
        if self.layout.action_kind == "categorical":
            index = action[:, 0].round().long().clamp(0, self.layout.action_size - 1)
            return F.one_hot(index, self.layout.action_size).to(action.dtype if action.is_floating_point() else torch.float32)
        return action.to(torch.float32)
