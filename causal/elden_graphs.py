"""ELDEN's local dependency graphs (eq. 5.1), the attention baseline of Table 5.1, and the
intrinsic reward of Algorithm 6: all for a whole batch at once.

Local graphs are partial derivatives of each member's prediction of the observed next value with
respect to its inputs, ``|d p(s^j_{t+1}) / d s^i_t|``, computed with ``torch.func.jacrev``
over the encoded inputs of the whole batch and every member at once (``d_S`` vector-Jacobian
products, one per output factor, batched by ``vmap`` inside ``jacrev``).
"""
from __future__ import annotations

import torch
from torch.func import jacrev

from causal.elden import ELDENModel, Targets


def jacobian_graphs(model: ELDENModel, x: torch.Tensor, targets: Targets) -> torch.Tensor:
    """Per-member local-graph scores ``[M, B, d_S, d_S + 1]`` for encoded inputs ``x`` and their
    targets: shared by every member (``x`` [B, T, W]) or one batch per member (``x`` [M, B, T, W]).
    :func:`input_jacobian` reduced per input variable (:meth:`ELDENModel.reduce_inputs`)."""
    inputs = model.per_member(x)
    return model.reduce_inputs(input_jacobian(model, inputs, targets), inputs[:, :, None])


def input_jacobian(model: ELDENModel, inputs: torch.Tensor, targets: Targets) -> torch.Tensor:
    """``d q(s^j_{t+1}) / d x`` for every member, sample, output and input entry, ``[M, B, d_S, T, W]``,
    of every member's inputs ``[M, B, T, W]``.

    ``jacrev`` of the quantity summed over members and samples, with respect to every member's
    copy of the inputs: a sample's output depends on that sample's inputs only, so this is each
    sample's own Jacobian (what ``vmap`` over samples gives) from ``d_S`` batched vector-Jacobian
    products over the whole batch."""
    params = model.params()

    def summed(xs: torch.Tensor) -> torch.Tensor:
        return model.graph_quantity(model.raw(params, xs), targets).sum(dim=(0, 1))

    return jacrev(summed)(inputs).movedim(0, 2)  # jacrev puts the outputs first: [d_S, M, B, T, W]


@torch.no_grad()
def member_local_graphs(model: ELDENModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                        chunk: int = 256) -> torch.Tensor:
    """Every member's local-graph scores of these transitions, ``[M, B, d_S, d_S + 1]``, in chunks."""
    parts = []
    for start in range(0, state.shape[0], chunk):
        s, a, n = (t[start : start + chunk] for t in (state, action, next_state))
        with torch.enable_grad():
            parts.append(jacobian_graphs(model, model.encode(s, a), model.targets(s, n)).detach())
    return torch.cat(parts, dim=1) if parts else torch.zeros(model.cfg.members, 0, model.num_outputs, model.num_inputs)


def local_graphs(model: ELDENModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
    """ELDEN's estimate of each transition's local graph: the members' scores averaged, ``[B, d_S, d_S + 1]``."""
    return member_local_graphs(model, state, action, next_state).mean(dim=0)


@torch.no_grad()
def attention_graphs(model: ELDENModel, state: torch.Tensor, action: torch.Tensor,
                     chunk: int = 512) -> torch.Tensor:
    """The "Attn" baseline of Table 5.1 on ELDEN's own network: ``sum_k attn(phi^i, theta^k)
    attn(theta^k, s^j)``, attention averaged over heads, the self-attention layers composed
    (``theta^k`` reads ``phi^i`` through every layer), averaged over members: ``[B, d_S, d_S + 1]``."""
    parts = []
    for start in range(0, state.shape[0], chunk):
        maps, out = model.attention_maps(model.encode(state[start : start + chunk], action[start : start + chunk]))
        reach = maps[:, 0].mean(dim=2)
        for layer in range(1, maps.shape[1]):
            reach = maps[:, layer].mean(dim=2) @ reach
        parts.append((out.mean(dim=2) @ reach).mean(dim=0))
    return torch.cat(parts) if parts else torch.zeros(0, model.num_outputs, model.num_inputs)


@torch.no_grad()
def graph_variance(model: ELDENModel, state: torch.Tensor, action: torch.Tensor,
                   next_state: torch.Tensor) -> torch.Tensor:
    """Algorithm 6, line 5, on these transitions (:func:`edge_variance` of the members' local graphs,
    outputs agreeing where every member predicts the same most likely class), ``[B]``. A continuous
    factor's members never agree exactly, so its edges always count."""
    members = member_local_graphs(model, state, action, next_state)
    agree = torch.zeros(state.shape[0], model.num_outputs, dtype=torch.bool)
    if model.codec.cat_factors:
        classes = model.predicted_classes(model(model.encode(state, action)))
        agree[:, model.codec.cat_index] = (classes == classes[:1]).all(dim=0)
    return edge_variance(members, model.cfg.edge_threshold, agree)


def edge_variance(member_graphs: torch.Tensor, threshold: float, agree: torch.Tensor) -> torch.Tensor:
    """The variance across members (dim 0) of each edge of the thresholded graphs ``[M, B, d_S, d_S + 1]``,
    zero in the rows of outputs where ``agree`` [B, d_S], averaged over every edge: ``[B]``."""
    variance = (member_graphs >= threshold).float().var(dim=0, unbiased=False)
    return variance.masked_fill(agree[..., None], 0.0).mean(dim=(1, 2))
