"""Causal Dynamics Learning (dissertation ch. 3): the masked, factored dynamics model of Fig. 3.3.

For every next-state factor ``s^j_{t+1}`` the model has one feature network per input (each state
factor and the action), masks features to ``-inf`` with a binary mask ``M``, aggregates them by an
element-wise max and predicts the distribution of ``s^j_{t+1}`` with a per-factor head (Normal for a
continuous factor, categorical for a discrete one). All ``d_S x (d_S + 1)`` feature networks and the
``d_S`` heads are stacked tensors driven by ``bmm``/``einsum``: one forward pass serves every output,
and the three likelihood terms of eq. 3.3 (full, one input dropped, causal parents) share one feature
computation because masks only act after it.

The max over inputs is computed once as a top-2, so "drop input i" for *every* i costs no more than
one max: where input i is the arg-max, the second-largest value takes its place. That is what makes
the all-pairs CMI of eq. 3.2 a single batched pass.

Layout of the feature tensor: ``[J, I, B, F]`` = (output factor, input, sample, feature).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from causal.cdl_max import _MaxAndDropOne, masked_max, max_and_runner_up, training_aggregates
from causal.factored import FactorCodec, FactorLayout
from causal.method import layout_from_config
from causal.method import model_config_json as method_config_json
from causal.schedules import cosine_lr
from proto.settings import doc

LOG_2PI = math.log(2 * math.pi)
TRAIN_PRECISIONS = ("fp32", "bf16")
TARGETS = ("delta", "next")
_LOW = {"fp32": None, "bf16": torch.bfloat16}
__all__ = ["CDLConfig", "CDLModel", "FeatureGroup", "model_config_json", "model_from_config", "model_from_config_json",
           "_MaxAndDropOne", "masked_max", "max_and_runner_up"]  # the last three re-exported (causal.cbm_implicit)


@dataclass(frozen=True)
class CDLConfig:
    """CDL (ch. 3): architecture and optimisation of the masked dynamics model, and its CMI edge threshold."""

    feature_hidden: int = doc(32, "hidden width of each per-(output, input) feature network (reference: 64; "
                                  "see docs/deviations.md)")
    feature_dim: int = doc(32, "size of every feature vector phi^i (all features share one size, as the "
                               "chapter requires)")
    predictor_hidden: int = doc(64, "hidden width of each per-output predictive head (reference: 64 -> 64 -> 64)")
    lr: float = doc(3e-3, "Adam learning rate (the reference's 1e-4 over 500k updates is ~40x more updates "
                          "than a run here makes; see docs/deviations.md)")
    lr_decay_updates: int = doc(0, "cosine decay of the learning rate from lr to lr_final over this many "
                                   "updates, constant after (0: constant lr; not in the chapter)")
    lr_final: float = doc(1e-4, "learning rate at the end of the decay (the reference's constant rate)")
    batch_size: int = doc(64, "transitions per update")
    causal_every: int = doc(10, "include the causal-parents likelihood term once every this many updates "
                                "(ch. 3.3.2)")
    log_std_min: float = doc(-6.0, "lower clip of a continuous head's log standard deviation")
    log_std_max: float = doc(2.0, "upper clip of a continuous head's log standard deviation")
    grad_clip: float = doc(10.0, "gradient norm clip")
    cmi_threshold: float = doc(0.02, "CMI edge threshold epsilon_G, nats: edge if CMI >= this (also the "
                                     "point-wise CMI threshold of local graphs)")
    train_precision: str = doc("fp32", "matrix products of the training update: fp32, or bf16 (bfloat16 "
                                       "products of the feature networks and heads; weights, biases, the max "
                                       "aggregation, losses and optimiser stay fp32, and CMI and every "
                                       "evaluation stay fp32; ~4x faster products on CPUs with AVX512-BF16; "
                                       "see docs/deviations.md)", choices=TRAIN_PRECISIONS)
    target: str = doc("delta", "what a continuous head's Gaussian scores: the factor's change s_{t+1} - s_t "
                               "(delta: the chapter's and the authors' model) or its next value s_{t+1} (next: "
                               "CBM's explicit variant under --cbm-target next; see docs/methods/cbm.md)",
                      choices=TARGETS)

    def __post_init__(self) -> None:
        for name in ("lr", "lr_final", "grad_clip"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value}")
        for name in ("feature_hidden", "feature_dim", "predictor_hidden", "batch_size", "causal_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.lr_decay_updates < 0:
            raise ValueError(f"lr_decay_updates must be >= 0, got {self.lr_decay_updates}")
        if not (math.isfinite(self.cmi_threshold) and self.cmi_threshold >= 0):
            raise ValueError(f"cmi_threshold must be a finite number >= 0, got {self.cmi_threshold}")
        if self.target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {self.target!r}")
        if self.train_precision not in TRAIN_PRECISIONS:
            raise ValueError(f"train_precision must be one of {TRAIN_PRECISIONS}, got {self.train_precision!r}")
        if not self.log_std_min < self.log_std_max:
            raise ValueError(f"log_std_min ({self.log_std_min}) must be below log_std_max ({self.log_std_max})")

    def lr_at(self, updates: int) -> float:
        """The learning rate of update number ``updates`` (0-based) under the cosine schedule."""
        return cosine_lr(self.lr, self.lr_final, updates, self.lr_decay_updates)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)



def _affine(bias: torch.Tensor, x: torch.Tensor, weight: torch.Tensor, low: torch.dtype | None) -> torch.Tensor:
    """``baddbmm(bias, x, weight)``; with ``low`` (the training update's ``train_precision``), the
    product in that dtype, cast to fp32, and the bias added in fp32.

    Adding each network's own fp32 bias after the product keeps exact ties between two inputs'
    features as improbable as in fp32, which the max aggregation's gradient routing assumes
    (:mod:`causal.cdl_max`). The cast and an in-place add are two vectorised passes; the one-pass
    ``torch.add(bias, product)`` with type promotion takes a slow path on the CPU, ~20x slower (it was
    the largest single operator of a bf16 update)."""
    if low is None:
        return torch.baddbmm(bias, x, weight)
    return torch.bmm(x.to(low), weight.to(low)).to(torch.float32).add_(bias)


def _stacked(*shape: int, fan_in: int) -> nn.Parameter:
    bound = 1.0 / math.sqrt(fan_in)
    return nn.Parameter(torch.empty(*shape).uniform_(-bound, bound))


class _ScalarNetworks(torch.autograd.Function):
    """Feature networks of scalar inputs, ``w2 relu(w1 x + b1) + b2`` for every (output, input), with
    a hand-written backward: features [J, K, B, F] from inputs [B, K], written between the features
    ``head`` [J, K_h, B, F] and ``tail`` [J, K_t, B, F] of the other inputs (either may be None):
    [J, K_h + K + K_t, B, F], the concatenation along inputs.

    The same products as :meth:`FeatureGroup.dense` (in ``low`` or fp32, the bias added in fp32), and
    the gradients autograd would give, to the products' rounding. Autograd's backward of that chain
    spent about as long in copies and casts as in the products: the gradient arrived as a strided
    slice of the concatenated features, was made contiguous and then cast; each weight's gradient was
    cast back through its own ``to``; the first layer's weight gradient was a product and a sum over
    samples. Here the gradient is cast once (contiguous by the cast), the first layer's weight
    gradient is one batched product over samples, and the products are written into the
    concatenated tensor directly (no concatenation copy of the largest group). Inputs get no gradient
    (they are data), so :meth:`FeatureGroup.dense` uses this only when they need none."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, w1: torch.Tensor, b1: torch.Tensor, w2: torch.Tensor, b2: torch.Tensor,
                low: torch.dtype | None, head: torch.Tensor | None = None,
                tail: torch.Tensor | None = None) -> torch.Tensor:
        j, k, _, hidden = w1.shape
        n = x.shape[0]
        dtype = low or w1.dtype
        xs = x.T.contiguous()[None, :, :, None]  # [1, K, B, 1]; contiguous, so h is
        # the first layer (an outer product, no matmul) in fp32 and h rounded once: a bf16 addcmul
        # converts every operand per element and took twice as long as this and the cast together
        h = torch.addcmul(b1, xs, w1).relu_().to(dtype)  # [J, K, B, H]
        xs = xs.to(dtype)
        w2l = w2.to(dtype)
        ctx.save_for_backward(xs, h, w2l)
        k_head = 0 if head is None else head.shape[1]
        k_tail = 0 if tail is None else tail.shape[1]
        ctx.inputs = (k_head, k, k_tail)
        hs = h.view(j * k, n, hidden)
        if not k_head and not k_tail:
            return _affine(b2, hs, w2l, low).view(j, k, n, -1)
        # into the concatenation: the bf16 product is cast by the copy, its fp32 bias added in place
        product = torch.bmm(hs, w2l) if low is not None else torch.baddbmm(b2, hs, w2l)
        out = torch.empty(j, k_head + k + k_tail, n, product.shape[-1], dtype=b2.dtype, device=x.device)
        if k_head:
            out[:, :k_head] = head
        if k_tail:
            out[:, k_head + k:] = tail
        mid = out[:, k_head : k_head + k]
        mid.copy_(product.view(j, k, n, -1))
        if low is not None:
            mid.add_(b2.view(j, k, 1, -1))
        return out

    @staticmethod
    @once_differentiable  # the saved hidden layer has no graph: a second derivative would miss terms, so it raises
    def backward(ctx, grad: torch.Tensor):
        xs, h, w2l = ctx.saved_tensors
        k_head, k, k_tail = ctx.inputs
        j, _, n, hidden = h.shape
        mid = grad[:, k_head : k_head + k]
        grad_b2 = mid.sum(dim=2).view(j * k, 1, -1)
        g = mid.to(h.dtype).reshape(j * k, n, -1)  # a cast to bf16 of the strided slice is contiguous: one copy
        grad_w2 = torch.bmm(h.view(j * k, n, hidden).transpose(1, 2), g)
        gh = torch.ops.aten.threshold_backward(torch.bmm(g, w2l.transpose(1, 2)).view(j, k, n, hidden), h, 0)
        grad_w1 = torch.matmul(xs.transpose(2, 3), gh)  # [1, K, 1, B] @ [J, K, B, H]: the sum over samples
        dtype = grad.dtype  # the parameters' (fp32 when the products are in ``low``)
        grad_head = grad[:, :k_head] if k_head and ctx.needs_input_grad[6] else None
        grad_tail = grad[:, k_head + k:] if k_tail and ctx.needs_input_grad[7] else None
        return (None, grad_w1.to(dtype), gh.sum(dim=2, keepdim=True).to(dtype), grad_w2.to(dtype), grad_b2, None,
                grad_head, grad_tail)


class _Heads(torch.autograd.Function):
    """The heads' three layers of :meth:`CDLModel.predict` with products in ``low`` (the training
    update's bf16), ``relu(x w1 + b1) -> relu(. w2 + b2) -> . w3 + b3``, each bias added in fp32,
    with a hand-written backward.

    Forward and gradients are the values autograd gives for the same chain (tests/causal/test_cdl.py):
    every gradient that meets a product is rounded to ``low`` there either way, and a hidden layer's
    gradient leaves its product already in ``low``, so it is masked by the ReLU and summed for its
    bias there (in fp32 accumulation) rather than cast to fp32 and back. At batch 64 the heads' products are
    small and autograd's casts between them were a large part of their cost."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, w1: torch.Tensor, b1: torch.Tensor, w2: torch.Tensor, b2: torch.Tensor,
                w3: torch.Tensor, b3: torch.Tensor, low: torch.dtype) -> torch.Tensor:
        xl, w1l, w2l, w3l = x.to(low), w1.to(low), w2.to(low), w3.to(low)
        h1 = _affine(b1, xl, w1l, low).relu_().to(low)
        h2 = _affine(b2, h1, w2l, low).relu_().to(low)
        ctx.save_for_backward(xl, h1, h2, w1l, w2l, w3l)
        return _affine(b3, h2, w3l, low)

    @staticmethod
    @once_differentiable  # the saved layers have no graph: a second derivative would miss terms, so it raises
    def backward(ctx, grad: torch.Tensor):
        xl, h1, h2, w1l, w2l, w3l = ctx.saved_tensors
        fp32 = torch.float32
        gb3 = grad.sum(dim=1, keepdim=True)
        g = grad.to(xl.dtype)
        gw3 = torch.bmm(h2.transpose(1, 2), g).to(fp32)
        g = torch.ops.aten.threshold_backward(torch.bmm(g, w3l.transpose(1, 2)), h2, 0)
        gb2 = g.sum(dim=1, keepdim=True, dtype=fp32)
        gw2 = torch.bmm(h1.transpose(1, 2), g).to(fp32)
        g = torch.ops.aten.threshold_backward(torch.bmm(g, w2l.transpose(1, 2)), h1, 0)
        gb1 = g.sum(dim=1, keepdim=True, dtype=fp32)
        gw1 = torch.bmm(xl.transpose(1, 2), g).to(fp32)
        g = torch.bmm(g, w1l.transpose(1, 2))
        return g.to(fp32), gw1, gb1, gw2, gb2, gw3, gb3, None


class FeatureGroup(nn.Module):
    """Feature networks phi^{j,k}: width -> hidden -> feature, for K inputs of one kind and every output j.

    A categorical input is one-hot, so its network takes only ``width`` distinct values: ``table()``
    evaluates them once per call and samples gather their rows. That equals running the network on
    each one-hot vector, at a fraction of the cost.
    """

    def __init__(self, outputs: int, inputs: int, width: int, hidden: int, feature: int) -> None:
        super().__init__()
        self.shape = (outputs, inputs, width, hidden, feature)
        self.w1 = _stacked(outputs, inputs, width, hidden, fan_in=width)
        self.b1 = _stacked(outputs, inputs, 1, hidden, fan_in=width)
        self.w2 = _stacked(outputs * inputs, hidden, feature, fan_in=hidden)
        self.b2 = _stacked(outputs * inputs, 1, feature, fan_in=hidden)

    def _second_layer(self, h: torch.Tensor, low: torch.dtype | None = None) -> torch.Tensor:
        j, k, n, hidden = h.shape
        return _affine(self.b2, h.reshape(j * k, n, hidden), self.w2, low).view(j, k, n, -1)

    def dense(self, x: torch.Tensor, low: torch.dtype | None = None, fused: bool = False,
              head: torch.Tensor | None = None, tail: torch.Tensor | None = None) -> torch.Tensor:
        """Inputs [B, K, width] -> features [J, K, B, F] (fp32; ``low``: see :func:`_affine`).

        ``fused``: scalar inputs' networks by :class:`_ScalarNetworks` (CDL's :meth:`CDLModel.features`,
        for training and evaluation: the same features; first-order gradients of the parameters only,
        so not where a gradient of the inputs is taken, and a second-order one raises), placed between
        the features ``head`` and ``tail`` of the other inputs (concatenated along inputs). Other
        inputs than scalars, or inputs that need a gradient, take the plain path and the concatenation."""
        if fused and self.shape[2] == 1 and not x.requires_grad:
            return _ScalarNetworks.apply(x[:, :, 0], self.w1, self.b1, self.w2, self.b2, low, head, tail)
        if head is not None or tail is not None:
            return torch.cat([g for g in (head, self.dense(x, low), tail) if g is not None], dim=1)
        if self.shape[2] == 1:  # scalar inputs: the first layer is an outer product, no matmul needed
            x = x[None, :, :, 0].transpose(1, 2).contiguous()[..., None]  # contiguous: then so is h
            h = torch.addcmul(self.b1, x, self.w1)  # in fp32, as _ScalarNetworks makes it
        else:
            h = torch.einsum("bkw,jkwh->jkbh", x, self.w1) + self.b1
        return self._second_layer(torch.relu(h), low)

    def table(self, low: torch.dtype | None = None) -> torch.Tensor:
        """Features of every one-hot value: [J, K, width, F]."""
        return self._second_layer(torch.relu(self.w1 + self.b1), low)

    def onehot(self, index: torch.Tensor, low: torch.dtype | None = None) -> torch.Tensor:
        """Category indices [B, K] -> features [J, K, B, F]."""
        j, k, width, _, _ = self.shape
        flat = (torch.arange(k, device=index.device)[:, None] * width + index.T).reshape(-1)
        return self.table(low).reshape(j, k * width, -1).index_select(1, flat).view(j, k, index.shape[0], -1)

    def dense_pairs(self, x: torch.Tensor, outputs: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        """Features [P, B, F] of only the P (output, input) pairs ``outputs[p], inputs[p]`` from
        inputs [B, K, width]: the same networks as :meth:`dense`, evaluated for the listed pairs."""
        k = self.shape[1]
        h = torch.einsum("bpw,pwh->pbh", x[:, inputs], self.w1[outputs, inputs]) + self.b1[outputs, inputs]
        flat = outputs * k + inputs
        return torch.baddbmm(self.b2[flat], torch.relu(h), self.w2[flat])

    def onehot_pairs(self, index: torch.Tensor, outputs: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        """Features [P, B, F] of the listed pairs from category indices [B, K] (see :meth:`onehot`)."""
        h = torch.relu(self.w1[outputs, inputs] + self.b1[outputs, inputs])  # [P, width, hidden]
        flat = outputs * self.shape[1] + inputs
        table = torch.baddbmm(self.b2[flat], h, self.w2[flat])  # [P, width, F]
        return table.gather(1, index[:, inputs].T[..., None].expand(-1, -1, table.shape[-1]))


class CDLModel(nn.Module):
    """The d_S masked predictive models of Fig. 3.3 as one batched module.

    Inputs are kept in *group order* inside the module (categorical factors, continuous factors, the
    action); ``input_order`` maps group positions back to the graph's column order.
    """

    def __init__(self, layout: FactorLayout, cfg: CDLConfig) -> None:
        super().__init__()
        self.layout, self.cfg = layout, cfg
        self.codec = FactorCodec(layout)
        n, hf, f, h, o = layout.num_factors, cfg.feature_hidden, cfg.feature_dim, cfg.predictor_hidden, layout.head_width
        self.num_outputs, self.num_inputs = n, n + 1
        codec = self.codec
        self.cat_features = FeatureGroup(n, len(codec.cat_factors), codec.max_cat, hf, f) if codec.cat_factors else None
        self.cont_features = FeatureGroup(n, len(codec.cont_factors), codec.max_cont, hf, f) if codec.cont_factors else None
        self.action_features = FeatureGroup(n, 1, layout.action_width, hf, f)
        self.head_w1, self.head_b1 = _stacked(n, f, h, fan_in=f), _stacked(n, 1, h, fan_in=f)
        self.head_w2, self.head_b2 = _stacked(n, h, h, fan_in=h), _stacked(n, 1, h, fan_in=h)
        self.head_w3, self.head_b3 = _stacked(n, h, o, fan_in=h), _stacked(n, 1, o, fan_in=h)
        self.register_buffer("cat_class_mask", self._class_mask())
        order = torch.tensor(codec.cat_factors + codec.cont_factors + [n], dtype=torch.long)
        self.register_buffer("input_order", order)

    def _class_mask(self) -> torch.Tensor:
        cats = self.codec.cat_factors
        mask = torch.zeros(len(cats), self.codec.max_cat, dtype=torch.bool)
        for n, j in enumerate(cats):
            mask[n, : self.layout.sizes[j]] = True
        return mask

    def features(self, state: torch.Tensor, action: torch.Tensor, low: torch.dtype | None = None) -> torch.Tensor:
        """[J, I, B, F] features phi^i for every output j, input i (group order) and sample; always
        fp32 (``low``, the training update's precision, only sets the products': :func:`_affine`)."""
        head = None
        if self.cat_features is not None:
            index = self.codec.categories(state).clamp_max(self.codec.max_cat - 1)
            head = self.cat_features.onehot(index, low)
        if self.layout.action_kind == "categorical":
            index = action[:, :1].round().long().clamp(0, self.layout.action_size - 1)
            tail = self.action_features.onehot(index, low)
        else:
            tail = self.action_features.dense(action[:, None, :].to(torch.float32), low)
        if self.cont_features is not None:  # written between the two (group order), without a concatenation copy
            return self.cont_features.dense(self.codec.continuous_values(state), low, fused=True, head=head, tail=tail)
        return torch.cat([g for g in (head, tail) if g is not None], dim=1)

    def masked_outputs(self, state: torch.Tensor, action: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Raw head outputs [J, B, head_width] with each output's inputs restricted to ``mask``
        ([J, I] bool, graph column order; every row needs at least one input).

        Equal to masking :meth:`features` and aggregating, but only the kept (output, input) pairs'
        feature networks run: with a sparse causal graph that is a fraction of the all-pairs cost,
        which is what makes planning and k-step rollouts with the causal model cheap."""
        keep = self.to_group_order(mask.to(torch.bool))
        if not bool(keep.any(dim=1).all()):
            raise ValueError("every output needs at least one input in the mask")
        b = state.shape[0]
        aggregated = torch.full((self.num_outputs, b, self.cfg.feature_dim), float("-inf"), dtype=torch.float32,
                                device=state.device)
        offset = 0
        codec = self.codec
        groups = []
        if self.cat_features is not None:
            index = self.codec.categories(state).clamp_max(codec.max_cat - 1)
            groups.append((self.cat_features, lambda g, o, i, index=index: g.onehot_pairs(index, o, i)))
        if self.cont_features is not None:
            values = codec.continuous_values(state)
            groups.append((self.cont_features, lambda g, o, i, values=values: g.dense_pairs(values, o, i)))
        if self.layout.action_kind == "categorical":
            act = action[:, :1].round().long().clamp(0, self.layout.action_size - 1)
            groups.append((self.action_features, lambda g, o, i, act=act: g.onehot_pairs(act, o, i)))
        else:
            act = action[:, None, :].to(torch.float32)
            groups.append((self.action_features, lambda g, o, i, act=act: g.dense_pairs(act, o, i)))
        for group, run in groups:
            width = group.shape[1]
            outputs, inputs = torch.nonzero(keep[:, offset : offset + width], as_tuple=True)
            offset += width
            if len(outputs):
                feats = run(group, outputs, inputs)
                aggregated.scatter_reduce_(0, outputs[:, None, None].expand_as(feats), feats, "amax")
        return self.predict(aggregated[:, None])[:, 0]

    def to_group_order(self, mask: torch.Tensor) -> torch.Tensor:
        """A [J, I] mask in graph column order -> the module's input order."""
        return mask[:, self.input_order]

    def to_graph_order(self, matrix: torch.Tensor) -> torch.Tensor:
        """A [..., J, I] matrix in the module's input order -> graph column order."""
        out = torch.empty_like(matrix)
        out[..., self.input_order] = matrix
        return out

    def predict(self, aggregated: torch.Tensor, low: torch.dtype | None = None) -> torch.Tensor:
        """Heads on aggregated features [J, K, B, F] -> raw outputs [J, K, B, head_width] (fp32;
        ``low``: the products' dtype, :func:`_affine`)."""
        j, k, b, f = aggregated.shape
        x = aggregated.reshape(j, k * b, f)
        if low is not None:
            return _Heads.apply(x, self.head_w1, self.head_b1, self.head_w2, self.head_b2, self.head_w3,
                                self.head_b3, low).view(j, k, b, -1)
        x = torch.relu(_affine(self.head_b1, x, self.head_w1, low))
        x = torch.relu(_affine(self.head_b2, x, self.head_w2, low))
        return _affine(self.head_b3, x, self.head_w3, low).view(j, k, b, -1)

    def nll(self, out: torch.Tensor, state: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        """Negative log-likelihood [J, K, B] of the next state under outputs [J, K, B, O], in nats."""
        return self._nll_of(out, *self._targets(state, next_state))

    def _targets(self, state: torch.Tensor,
                 next_state: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """What the heads are scored against, per output and sample: the next class of each
        categorical output [J_cat, B] and the change (or, with ``cfg.target == "next"``, the next value)
        of each continuous output [J_cont, B, max_cont]."""
        codec = self.codec
        cat = codec.categories(next_state).T.clamp_max(codec.max_cat - 1) if codec.cat_factors else None
        delta = None
        if codec.cont_factors:
            delta = codec.continuous_values(next_state).permute(1, 0, 2)
            if self.cfg.target == "delta":
                delta = delta - codec.continuous_values(state).permute(1, 0, 2)
        return cat, delta

    def _nll_of(self, out: torch.Tensor, cat: torch.Tensor | None, delta: torch.Tensor | None) -> torch.Tensor:
        """NLL [J, K, N] of outputs [J, K, N, O] against :meth:`_targets` laid out [J_*, N(, m)]."""
        result = out.new_empty(out.shape[:3])
        codec = self.codec
        if cat is not None:
            logits = out[codec.cat_index, :, :, : codec.max_cat]
            logits = logits.masked_fill(~self.cat_class_mask[:, None, None, :], float("-inf"))
            logp = torch.log_softmax(logits, dim=-1)
            index = cat[:, None, :, None].expand(-1, out.shape[1], -1, 1)
            result[codec.cat_index] = -logp.gather(-1, index).squeeze(-1)
        if delta is not None:
            m = codec.max_cont
            raw = out[codec.cont_index]
            log_std = raw[..., m : 2 * m].clamp(self.cfg.log_std_min, self.cfg.log_std_max)
            z = (delta[:, None] - raw[..., :m]) * torch.exp(-log_std)
            per_dim = 0.5 * z.square() + log_std + 0.5 * LOG_2PI
            result[codec.cont_index] = (per_dim * codec.cont_valid[:, None, None, :]).sum(-1)
        return result

    def masked_nll(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                   mask: torch.Tensor) -> torch.Tensor:
        """NLL [J, B] with inputs masked by ``mask`` [J, I] (True = input used)."""
        feats = self.features(state, action)
        keep = self.to_group_order(mask)
        agg = masked_max(feats, keep)
        return self.nll(self.predict(agg), state, next_state)[:, 0]

    def training_nll(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                     parents: torch.Tensor | None, generator: torch.Generator | None = None) -> torch.Tensor:
        """The terms of eq. 3.3 as NLL [J, K, B]: K = full, one uniformly dropped input, causal parents.

        The heads run on the full aggregate of every (output, sample) and on the dropped / causal
        aggregates only where they differ from it (:func:`causal.cdl_max.training_aggregates`);
        every other row's term is the full one's NLL, the same value and gradient as running the
        heads on it (tests/causal/test_cdl.py); all those rows go through the heads in one pass
        (:meth:`_packed_nll`). The products run in ``cfg.train_precision``
        (:func:`_affine`); everything else in fp32."""
        low = _LOW[self.cfg.train_precision]
        feats = self.features(state, action, low)
        drop = torch.randint(0, self.num_inputs, (self.num_outputs, 1, state.shape[0], 1),
                             generator=generator).to(feats.device)  # drawn on the CPU: the same draws on any device
        excluded = None if parents is None else ~self.to_group_order(parents)
        first, dropped, kept, d_j, d_b, c_j, c_b = training_aggregates(feats, drop, excluded)
        groups = [(d_j, d_b, dropped)] + ([(c_j, c_b, kept)] if parents is not None else [])
        # one pass of the heads over every row of every term (the full aggregates lead): three passes
        # of small products cost three times the operators' overhead, which at batch 64 is most of it
        nll, at = self._packed_nll(first, groups, *self._targets(state, next_state), low)
        full = nll.view(self.num_outputs, -1)[:, : state.shape[0]]
        terms = [full] + [full.index_put((out_j, sample), nll[places]) if len(out_j) else full
                          for (out_j, sample, _), places in zip(groups, at)]
        return torch.stack(terms, dim=1)

    def constant_inputs(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """[I] bool, graph column order: inputs (state factors, then the action) that take a single
        value over all of these samples."""
        same = torch.cat([(state == state[:1]).all(dim=0), (action == action[:1]).all(dim=0).all()[None]])
        slots = [self.layout.slots(j) for j in range(self.num_outputs)] + [1]
        owner = torch.repeat_interleave(torch.arange(self.num_inputs, device=state.device),
                                        torch.tensor(slots, device=state.device))
        return torch.zeros(self.num_inputs, dtype=torch.long, device=state.device).index_add_(0, owner, (~same).long()) == 0

    def drop_one_gain(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        """NLL(input i dropped) - NLL(full) per output j, input i and sample: ``[J, I, B]`` nats, in
        the module's input order; one feature computation for every i (the top-2 max).

        Dropping an input that is the arg-max of none of a sample's F features leaves the aggregate
        unchanged, so its gain is exactly 0; the heads run only on the (j, i, sample) rows whose
        input wins some feature (at most min(I, F) per output and sample, often far fewer), not on
        all J x I x B of them: at 40 objects the heads on every drop-one aggregate were most of an
        evaluation's time (docs/results.md, "CDL at scale"). Equal to running them everywhere
        (tests/causal/test_cdl.py)."""
        first, runner_up, is_max = max_and_runner_up(self.features(state, action))
        cat, delta = self._targets(state, next_state)
        full_nll = self._nll_of(self.predict(first), cat, delta)[:, 0]
        wins = is_max.any(dim=-1)
        gain = full_nll.new_zeros(wins.shape)
        out_j, in_i, sample = wins.nonzero(as_tuple=True)
        if not len(out_j):
            return gain
        dropped = torch.where(is_max[out_j, in_i, sample], runner_up[out_j, 0, sample], first[out_j, 0, sample])
        gain[out_j, in_i, sample] = self._nll_of_rows(out_j, sample, dropped, cat, delta) - full_nll[out_j, sample]
        return gain

    def permuted_gain(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                      other_state: torch.Tensor, other_action: torch.Tensor) -> torch.Tensor:
        """NLL(input i's value taken from another sample) - NLL(full) per output j, input i and sample:
        ``[J, I, B]`` nats, module input order; sample b's input i is read from ``other_state[b]`` /
        ``other_action[b]`` (a permutation of the held-out set), every other input from its own.

        Each input's feature depends on that input alone, so swapping it is swapping its feature row;
        the heads run only where the swap changes the aggregate (the input won some feature, or its
        swapped feature does). For the permuted-input null of :mod:`causal.edge_tests`."""
        first, runner_up, is_max = max_and_runner_up(self.features(state, action))
        permuted = torch.maximum(torch.where(is_max, runner_up, first), self.features(other_state, other_action))
        cat, delta = self._targets(state, next_state)
        full_nll = self._nll_of(self.predict(first), cat, delta)[:, 0]
        gain = full_nll.new_zeros(is_max.shape[:3])
        out_j, in_i, sample = (permuted != first).any(dim=-1).nonzero(as_tuple=True)
        if not len(out_j):
            return gain
        rows = permuted[out_j, in_i, sample]
        gain[out_j, in_i, sample] = self._nll_of_rows(out_j, sample, rows, cat, delta) - full_nll[out_j, sample]
        return gain

    def _nll_of_rows(self, out_j: torch.Tensor, sample: torch.Tensor, aggregated_rows: torch.Tensor,
                     cat: torch.Tensor | None, delta: torch.Tensor | None) -> torch.Tensor:
        """NLL ``[N]`` of output ``out_j[n]``'s head on ``aggregated_rows[n]`` against sample ``sample[n]``'s
        target; ``out_j`` sorted (as ``nonzero`` gives it)."""
        nll, (places,) = self._packed_nll(None, [(out_j, sample, aggregated_rows)], cat, delta)
        return nll[places]

    def _packed_nll(self, lead: torch.Tensor | None,
                    groups: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
                    cat: torch.Tensor | None, delta: torch.Tensor | None,
                    low: torch.dtype | None = None) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """The heads' NLL of many aggregates in one pass: ``lead`` [J, L, F] (every output's aggregate
        of samples 0..L-1; None: L = 0), then each group ``(out_j [N], sample [N], rows [N, F])``: row
        n is output ``out_j[n]``'s aggregate of sample ``sample[n]`` (``out_j`` sorted, as ``nonzero``
        gives it). Rows are packed per output after the lead, each group padded to the most rows any
        output has in it: NLL ``[J * W]`` (row-major [J, W]) and, per group, the [N] positions of its
        rows' NLL in it."""
        j = self.num_outputs
        width = 0 if lead is None else lead.shape[1]
        columns = []  # each group's rows after the lead and the groups before it, in order per output
        for out_j, _, _ in groups:
            counts = torch.bincount(out_j, minlength=j)
            columns.append(width + torch.arange(len(out_j), device=out_j.device) - (torch.cumsum(counts, 0) - counts)[out_j])
            width += int(counts.max()) if len(out_j) else 0
        places = [out_j * width + column for (out_j, _, _), column in zip(groups, columns)]
        like = lead if lead is not None else groups[0][2]
        feature = like.shape[-1]
        aggregated = like.new_zeros(j * width, feature)
        samples = torch.zeros(j * width, dtype=torch.long, device=like.device)
        if lead is not None:
            aggregated.view(j, width, feature)[:, : lead.shape[1]] = lead
            samples.view(j, width)[:, : lead.shape[1]] = torch.arange(lead.shape[1], device=like.device)
        for (_, sample, rows), at in zip(groups, places):
            if len(at):  # whole rows into a flat [J * W, F] view (two index tensors are several times slower)
                aggregated.index_copy_(0, at, rows)
                samples[at] = sample
        samples = samples.view(j, width)
        codec = self.codec
        cat_rows = cat.gather(1, samples[codec.cat_index]) if cat is not None else None
        delta_rows = None
        if delta is not None:
            delta_rows = delta.gather(1, samples[codec.cont_index, :, None].expand(-1, -1, delta.shape[-1]))
        out = self.predict(aggregated.view(j, 1, width, feature), low)
        return self._nll_of(out, cat_rows, delta_rows).view(-1), places

    @torch.no_grad()
    def cmi(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
            chunk: int = 256, zero_constant_inputs: bool = True) -> torch.Tensor:
        """CMI^{ij} of eq. 3.2 for every output j and input i: mean NLL(drop i) - NLL(full), [J, I] nats.

        An input that is constant over the samples has CMI exactly 0 (a constant is independent of
        everything), and its column is set so. The network's estimate there is not 0: a constant
        input's feature is a constant vector that the max can use as a floor, a learned bias, and
        the drop-one model is trained less than the full one, so dropping it costs a little
        likelihood and reads as an edge. On manipulation this made the markers' constant ``z``
        parents of the robot and ``mov`` (false edges, and markers in the action-relevant class).
        ``zero_constant_inputs=False`` returns the network's estimate everywhere (for comparison)."""
        total = torch.zeros(self.num_outputs, self.num_inputs, device=state.device)
        for start in range(0, state.shape[0], chunk):
            s, a, n = (t[start : start + chunk] for t in (state, action, next_state))
            total += self.drop_one_gain(s, a, n).sum(dim=-1)
        cmi = self.to_graph_order(total / max(state.shape[0], 1))
        if zero_constant_inputs and state.shape[0]:
            cmi[:, self.constant_inputs(state, action)] = 0.0
        return cmi

    @torch.no_grad()
    def pointwise_cmi(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                      chunk: int = 256) -> torch.Tensor:
        """Point-wise CMI of every transition (the local graph estimate of chapters 5-6, "pCMI"):
        ``log p(s'_j | s, a) - log p(s'_j | s without i, a)`` per sample, ``[B, J, I]`` nats, graph
        column order. Its mean over samples is :meth:`cmi` (without the constant-input zeroing)."""
        out = torch.empty(state.shape[0], self.num_outputs, self.num_inputs, device=state.device)
        for start in range(0, state.shape[0], chunk):
            s, a, n = (t[start : start + chunk] for t in (state, action, next_state))
            out[start : start + chunk] = self.to_graph_order(self.drop_one_gain(s, a, n).permute(2, 0, 1))
        return out


def model_config_json(layout: FactorLayout, cfg: CDLConfig) -> str:
    """Everything needed to rebuild a CDLModel from published weights."""
    return method_config_json("cdl", layout, cfg)


def model_from_config(data: dict) -> CDLModel:
    """A CDLModel (untrained) from a parsed :func:`model_config_json`."""
    if data.get("model") != "cdl":
        raise ValueError(f"not a CDL model config: {data.get('model')!r}")
    return CDLModel(layout_from_config(data), CDLConfig(**data["cdl"]))


def model_from_config_json(text: str) -> CDLModel:
    return model_from_config(json.loads(text))
