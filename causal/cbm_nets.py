"""CBM's masked networks: CDL's per-input feature layer (Fig. 3.3) for any number of outputs, and
stacked per-output MLP heads.

Chapter 4 combines its predictive models into one network conditioned by a binary input mask M
(Fig. 4.2 (a)): the implicit dynamics (``d_S`` outputs, one per next factor) and the reward model (one
output) are both "per-input features, masked to -inf, aggregated by an element-wise max, then a
head", which is what these modules compute. Masks act after the features, so the full model and
every drop-one model share one feature computation (the top-2 max of :mod:`causal.cdl`).

Feature tensors are ``[J, I, B, F]`` (output, input in *group order*, sample, feature); group order is
categorical factors, continuous factors, the action; ``input_order`` maps it to the graph's columns.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from causal.cdl import FeatureGroup
from causal.factored import FactorCodec, FactorLayout


class MaskedFeatures(nn.Module):
    """Feature networks phi^{j,i}: one per (output j, input i), inputs being the state factors and the action."""

    def __init__(self, layout: FactorLayout, outputs: int, hidden: int, feature: int) -> None:
        super().__init__()
        self.layout, self.codec = layout, FactorCodec(layout)
        codec = self.codec
        self.num_outputs, self.num_inputs, self.feature_dim = outputs, layout.num_factors + 1, feature
        cat, cont = len(codec.cat_factors), len(codec.cont_factors)
        self.cat = FeatureGroup(outputs, cat, codec.max_cat, hidden, feature) if cat else None
        self.cont = FeatureGroup(outputs, cont, codec.max_cont, hidden, feature) if cont else None
        self.act = FeatureGroup(outputs, 1, layout.action_width, hidden, feature)
        order = torch.tensor(codec.cat_factors + codec.cont_factors + [layout.num_factors], dtype=torch.long)
        self.register_buffer("input_order", order)

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``[J, I, B, F]`` features of every input for every output (group order)."""
        groups = []
        if self.cat is not None:
            groups.append(self.cat.onehot(self.codec.categories(state).clamp_max(self.codec.max_cat - 1)))
        if self.cont is not None:
            groups.append(self.cont.dense(self.codec.continuous_values(state)))
        if self.layout.action_kind == "categorical":
            groups.append(self.act.onehot(action[:, :1].round().long().clamp(0, self.layout.action_size - 1)))
        else:
            groups.append(self.act.dense(action[:, None, :].to(torch.float32)))
        return torch.cat(groups, dim=1)

    def to_group_order(self, mask: torch.Tensor) -> torch.Tensor:
        """A ``[..., I]`` mask or matrix in graph column order -> group order."""
        return mask[..., self.input_order]

    def to_graph_order(self, matrix: torch.Tensor) -> torch.Tensor:
        """A ``[..., I]`` matrix in group order -> graph column order."""
        out = torch.empty_like(matrix)
        out[..., self.input_order] = matrix
        return out


def masked_max(feats: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """Aggregate ``[J, I, B, F]`` over inputs kept by ``keep`` (``[J, I]`` bool, group order) -> ``[J, 1, B, F]``."""
    return feats.masked_fill(~keep[:, :, None, None], float("-inf")).amax(dim=1, keepdim=True)


def stacked(*shape: int, fan_in: int) -> nn.Parameter:
    """A stacked weight initialised as ``nn.Linear`` initialises one of fan-in ``fan_in``."""
    bound = 1.0 / math.sqrt(fan_in)
    return nn.Parameter(torch.empty(*shape).uniform_(-bound, bound))


class StackedMLP(nn.Module):
    """``J`` independent MLPs ``widths[0] -> ... -> widths[-1]`` (ReLU between), run as one batched module."""

    def __init__(self, outputs: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        self.weights = nn.ParameterList(stacked(outputs, a, b, fan_in=a) for a, b in zip(widths, widths[1:]))
        self.biases = nn.ParameterList(stacked(outputs, 1, b, fan_in=a) for a, b in zip(widths, widths[1:]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``[J, K, B, widths[0]]`` -> ``[J, K, B, widths[-1]]``."""
        j, k, b, _ = x.shape
        h = x.reshape(j, k * b, -1)
        for n, (w, bias) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(bias, h, w)
            if n < len(self.weights) - 1:
                h = torch.relu(h)
        return h.view(j, k, b, -1)


def constant_inputs(layout: FactorLayout, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """``[I]`` bool, graph column order: inputs (factors, then the action) that take a single value over
    these samples. Their CMI is exactly 0 (a constant is independent of everything); a network's
    estimate there is not (see :meth:`causal.cdl.CDLModel.cmi`), so estimators set it so."""
    same = torch.cat([(state == state[:1]).all(dim=0), (action == action[:1]).all(dim=0).all()[None]])
    slots = [layout.slots(j) for j in range(layout.num_factors)] + [1]
    owner = torch.repeat_interleave(torch.arange(layout.num_factors + 1), torch.tensor(slots))
    return torch.zeros(layout.num_factors + 1, dtype=torch.long).index_add_(0, owner, (~same).long()) == 0
