"""ELDEN's dynamics model (dissertation ch. 5, Fig. 5.3a): an ensemble of factored attention models.

Each member reads one token per state factor and one for the action: a per-token MLP gives the
features ``phi^i``, multi-head self-attention over the tokens gives ``theta^i``, and for every
next-state factor ``j`` a multi-head attention with ``theta^j`` as its query reads all tokens and a
per-factor head predicts ``p(s^j_{t+1} | s_t, a_t)``: categorical logits for a categorical factor, a
Normal (mean residual to the current value, clipped log-std) for a continuous one, as CDL's heads
(:mod:`causal.cdl`). The trunk (token MLPs and self-attention) is shared by the outputs of a member
(the chapter draws one such network per output factor; see ``docs/methods/elden.md``).

All parameters are stacked over the members (leading dimension ``M``) and :func:`ensemble_forward`
runs every member at once, each on its own inputs, with batched matrix products. Inputs are encoded *densely* (one-hot rows for categorical factors and the action,
normalised values for continuous ones, zero-padded to a common width ``W``), so that partial
derivatives with respect to them exist (eq. 5.1; Mixup makes them meaningful for discrete factors).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from causal.factored import FactorCodec, FactorLayout
from causal.method import layout_from_config
from proto.settings import doc

LOG_2PI = math.log(2 * math.pi)
GRAPH_OF = ("probability", "log_probability")
MODULATION_EPS = 1e-6


@dataclass(frozen=True)
class ELDENConfig:
    """ELDEN (ch. 5): the attention ensemble, its training (eqs. 5.2-5.3, Mixup, prioritisation), its
    local graphs (eq. 5.1) and its intrinsic reward (Algorithm 6)."""

    members: int = doc(5, "dynamics models in the ensemble (reference: 5)")
    token_hidden: int = doc(32, "hidden width of each per-factor token MLP (reference: [64, 64]; see docs/deviations.md)")
    embed_dim: int = doc(32, "token feature size phi^i / theta^i (reference: 64)")
    attention_layers: int = doc(2, "self-attention layers over the factor tokens (reference: 2)")
    heads: int = doc(4, "attention heads (reference: 4)")
    predictor_hidden: int = doc(32, "hidden width of each per-factor output head (reference: 64)")
    lr: float = doc(1e-3, "Adam learning rate (reference: 1e-5, which does not converge within a run here; "
                          "see docs/deviations.md)")
    member_batch: int = doc(32, "transitions per member and update; the learner samples members x this "
                                "and each member trains on its own share (reference: 32)")
    grad_clip: float = doc(10.0, "gradient norm clip (reference: 10)")
    grad_reg: float = doc(1e-3, "lambda of eqs. 5.2-5.3: weight of sum_ij |d p(s^j_t+1) / d s^i_t| in the loss "
                                "(Table 5.2's best: 1e-2 Thawing, 1e-3 CarWash, 1e-4 Kitchen; released config: 0)")
    grad_reg_rows: int = doc(8, "rows per member on which the regulariser is estimated each update (0: all; an "
                                "unbiased estimate either way, the batch being random)")
    mixup: bool = doc(True, "Mixup (Beta(mixup_alpha, mixup_alpha) weights) over inputs, action and next-state "
                            "labels when the env has discrete factors or actions")
    mixup_alpha: float = doc(0.1, "Beta parameter of the Mixup weights (reference: 0.1)")
    graph_of: str = doc("log_probability", "what eq. 5.1 differentiates: the log-likelihood of the observed next "
                                           "value (the released code's loss; measured better, docs/deviations.md) "
                                           "or its probability (density), as the text writes it",
                        choices=GRAPH_OF)
    edge_threshold: float = doc(3e-4, "epsilon_d of eq. 5.1: edge if |partial derivative| >= this (reference: 3e-4)")
    log_std_min: float = doc(-6.0, "lower clip of a continuous head's log standard deviation")
    log_std_max: float = doc(2.0, "upper clip of a continuous head's log standard deviation")
    reward_warmup_env_steps: int = doc(20_000, "env steps (of the weights the reward reads) before the intrinsic "
                                               "reward is non-zero (reference: 20k)")
    prioritised: bool = doc(False, "prioritised dynamics replay: priority (1 - exp(-error))^priority_alpha "
                                   "(ch. 5: Minecraft and Kitchen; released config: off)")
    priority_alpha: float = doc(0.5, "exponent of the replay priorities (reference: 0.5)")

    def __post_init__(self) -> None:
        for name in ("members", "token_hidden", "embed_dim", "attention_layers", "heads", "predictor_hidden",
                     "member_batch"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.embed_dim % self.heads:
            raise ValueError(f"embed_dim ({self.embed_dim}) must be a multiple of heads ({self.heads})")
        for name in ("lr", "grad_clip", "mixup_alpha"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a positive finite number, got {getattr(self, name)}")
        for name in ("grad_reg", "edge_threshold", "priority_alpha"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {getattr(self, name)}")
        if self.graph_of not in GRAPH_OF:
            raise ValueError(f"graph_of must be one of {GRAPH_OF}, got {self.graph_of!r}")
        if self.grad_reg_rows < 0:
            raise ValueError(f"grad_reg_rows must be >= 0, got {self.grad_reg_rows}")
        if not self.log_std_min < self.log_std_max or self.reward_warmup_env_steps < 0:
            raise ValueError("log_std_min must be below log_std_max and reward_warmup_env_steps >= 0")

    @property
    def batch_size(self) -> int:
        return self.members * self.member_batch


class Targets(NamedTuple):
    """Prediction targets per sample: soft labels of the categorical factors ``[..., n_cat, max_cat]``
    (one-hot, or mixed by Mixup), and current / next normalised values of the continuous ones."""

    labels: torch.Tensor
    current: torch.Tensor
    following: torch.Tensor


def _stacked(*shape: int, fan_in: int) -> nn.Parameter:
    bound = 1.0 / math.sqrt(fan_in)
    return nn.Parameter(torch.empty(*shape).uniform_(-bound, bound))


def _linear(z: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """Per-member affine map: ``z`` [M, ..., D_in] -> [M, ..., D_out] (``weight`` [M, D_in, D_out])."""
    return torch.baddbmm(bias[:, None, :], z.flatten(1, -2), weight).view(*z.shape[:-1], weight.shape[-1])


def _norm(z: torch.Tensor, gain: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Layer norm with a per-member gain and shift ([M, D])."""
    shape = (gain.shape[0],) + (1,) * (z.dim() - 2) + (gain.shape[-1],)
    return F.layer_norm(z, z.shape[-1:]) * gain.view(shape) + shift.view(shape)


def _attention(p: dict[str, torch.Tensor], prefix: str, query: torch.Tensor, tokens: torch.Tensor,
               heads: int, modulation: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Multi-head attention of ``query`` [M, B, Q, D] over ``tokens`` [M, B, T, D] -> ([M, B, Q, D],
    weights [M, B, H, Q, T]).

    With ``modulation`` (values in [0, 1] broadcastable to the weights), the attention is kernel
    modulated (Rahaman et al. 2021; Weiss et al. 2022): ``K exp(s) / (eps + sum K exp(s))`` over the
    keys, so a key whose entry is 0 is not read at all, and a query whose entries are all 0 reads nothing."""
    d = tokens.shape[-1]
    q = _linear(query, p[prefix + "_wq"], p[prefix + "_bq"]).unflatten(-1, (heads, d // heads)).transpose(2, 3)
    kv = _linear(tokens, p[prefix + "_wkv"], p[prefix + "_bkv"]).unflatten(-1, (2, heads, d // heads))
    k, v = kv.select(-3, 0).transpose(2, 3), kv.select(-3, 1).transpose(2, 3)
    scores = q @ k.transpose(-1, -2) / math.sqrt(d // heads)
    if modulation is None:
        weights = torch.softmax(scores, dim=-1)
    else:
        scaled = modulation * torch.exp(scores - scores.amax(dim=-1, keepdim=True).detach())
        weights = scaled / (MODULATION_EPS + scaled.sum(dim=-1, keepdim=True))
    mixed = (weights @ v).transpose(2, 3).flatten(-2)
    return _linear(mixed, p[prefix + "_wo"], p[prefix + "_bo"]), weights


def token_features(p: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """Feature extraction: each token's own MLP, ``x`` [M, B, T, W] -> ``phi`` [M, B, T, D]."""
    h = torch.relu(torch.einsum("mbtw,mtwh->mbth", x, p["token_w1"]) + p["token_b1"][:, None])
    return torch.einsum("mbth,mthd->mbtd", h, p["token_w2"]) + p["token_b2"][:, None]


def interaction_layer(p: dict[str, torch.Tensor], layer: int, theta: torch.Tensor, heads: int,
                      modulation: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """One pre-norm self-attention block (attention, then feed-forward, each with a residual) of
    ``theta`` [M, B, T, D]; returns the new ``theta`` and the attention weights [M, B, H, T, T]."""
    lp = {k[3:]: v[:, layer] for k, v in p.items() if k.startswith("sa_")}
    z = _norm(theta, p["ln1_g"][:, layer], p["ln1_b"][:, layer])
    mixed, weights = _attention(lp, "at", z, z, heads, modulation)
    theta = theta + mixed
    z = _norm(theta, p["ln2_g"][:, layer], p["ln2_b"][:, layer])
    return theta + _linear(torch.relu(_linear(z, lp["ff_w1"], lp["ff_b1"])), lp["ff_w2"], lp["ff_b2"]), weights


def output_heads(p: dict[str, torch.Tensor], read: torch.Tensor) -> torch.Tensor:
    """Each output factor's head on what its attention read, [M, B, d_S, D] -> raw outputs [M, B, d_S, O]."""
    hidden = torch.relu(torch.einsum("mbjd,mjdp->mbjp", read, p["head_w1"]) + p["head_b1"][:, None])
    return torch.einsum("mbjp,mjpo->mbjo", hidden, p["head_w2"]) + p["head_b2"][:, None]


def ensemble_forward(p: dict[str, torch.Tensor], x: torch.Tensor, heads: int,
                     ) -> tuple[torch.Tensor, list[torch.Tensor], torch.Tensor]:
    """Every member on its own inputs: ``x`` [M, B, T, W] -> raw head outputs [M, B, d_S, O], the
    self-attention weights of each layer [M, B, H, T, T] and the output attention's [M, B, H, d_S, T].

    Each sample's outputs depend on that sample's inputs only (no batch statistics), so the gradient
    of a sum over samples is every sample's own gradient."""
    theta = token_features(p, x)
    maps = []
    for layer in range(p["ln1_g"].shape[1]):
        theta, weights = interaction_layer(p, layer, theta, heads)
        maps.append(weights)
    outputs = p["head_w1"].shape[1]
    z = _norm(theta, p["lno_g"], p["lno_b"])
    read, out_weights = _attention(p, "out", z[:, :, :outputs], z, heads)
    return output_heads(p, read), maps, out_weights


class ELDENModel(nn.Module):
    """The ensemble of Fig. 5.3a as stacked parameters (members first); tokens are in graph column
    order (the state factors, then the action)."""

    def __init__(self, layout: FactorLayout, cfg: ELDENConfig) -> None:
        super().__init__()
        self.layout, self.cfg = layout, cfg
        self.codec = FactorCodec(layout)
        n = layout.num_factors
        self.num_outputs, self.num_inputs = n, n + 1
        self.width = max(layout.input_width, layout.action_width)
        self._build(cfg.members, self.num_inputs, self.width, n, layout.head_width)
        self._register_input_buffers()

    def _build(self, m: int, t: int, w: int, j: int, o: int) -> None:
        cfg = self.cfg
        h, d, p, layers = cfg.token_hidden, cfg.embed_dim, cfg.predictor_hidden, cfg.attention_layers
        self.token_w1, self.token_b1 = _stacked(m, t, w, h, fan_in=w), _stacked(m, t, h, fan_in=w)
        self.token_w2, self.token_b2 = _stacked(m, t, h, d, fan_in=h), _stacked(m, t, d, fan_in=h)
        for name, shape in (("at_wq", (d, d)), ("at_wkv", (d, 2 * d)), ("at_wo", (d, d)),
                            ("ff_w1", (d, d)), ("ff_w2", (d, d))):
            setattr(self, "sa_" + name, _stacked(m, layers, *shape, fan_in=d))
            setattr(self, "sa_" + name.replace("_w", "_b"), nn.Parameter(torch.zeros(m, layers, shape[1])))
        for name in ("ln1", "ln2"):
            setattr(self, name + "_g", nn.Parameter(torch.ones(m, layers, d)))
            setattr(self, name + "_b", nn.Parameter(torch.zeros(m, layers, d)))
        self.lno_g, self.lno_b = nn.Parameter(torch.ones(m, d)), nn.Parameter(torch.zeros(m, d))
        for name, shape in (("out_wq", (d, d)), ("out_wkv", (d, 2 * d)), ("out_wo", (d, d))):
            setattr(self, name, _stacked(m, *shape, fan_in=d))
            setattr(self, name.replace("_w", "_b"), nn.Parameter(torch.zeros(m, shape[1])))
        self.head_w1, self.head_b1 = _stacked(m, j, d, p, fan_in=d), _stacked(m, j, p, fan_in=d)
        self.head_w2, self.head_b2 = _stacked(m, j, p, o, fan_in=p), _stacked(m, j, o, fan_in=p)

    def _register_input_buffers(self) -> None:
        layout, codec = self.layout, self.codec
        valid = torch.zeros(self.num_inputs, self.width, dtype=torch.bool)
        onehot = torch.zeros(self.num_inputs, dtype=torch.bool)
        for i in range(layout.num_factors):
            categorical = layout.kinds[i] == "categorical"
            valid[i, : codec.max_cat if categorical else layout.sizes[i]] = True
            onehot[i] = categorical
        valid[-1, : layout.action_width] = True
        onehot[-1] = layout.action_kind == "categorical"
        self.register_buffer("input_valid", valid)
        self.register_buffer("input_onehot", onehot)
        classes = torch.zeros(len(codec.cat_factors), codec.max_cat, dtype=torch.bool)
        for n, j in enumerate(codec.cat_factors):
            classes[n, : layout.sizes[j]] = True
        self.register_buffer("cat_class_mask", classes)
        order = torch.argsort(torch.tensor(codec.cat_factors + codec.cont_factors, dtype=torch.long))
        self.register_buffer("output_order", order)

    def params(self) -> dict[str, torch.Tensor]:
        """The stacked parameters by name (each with the member dimension first)."""
        return dict(self.named_parameters())

    def encode(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Flat states and actions -> dense token inputs ``[B, T, W]``."""
        x = F.pad(self.codec.encode_state(state), (0, self.width - self.layout.input_width))
        a = F.pad(self.codec.encode_action(action), (0, self.width - self.layout.action_width))
        return torch.cat([x, a[:, None]], dim=1)

    def targets(self, state: torch.Tensor, next_state: torch.Tensor) -> Targets:
        codec = self.codec
        labels = F.one_hot(codec.categories(next_state).clamp_max(codec.max_cat - 1), codec.max_cat).float()
        return Targets(labels, codec.continuous_values(state), codec.continuous_values(next_state))

    def per_member(self, x: torch.Tensor) -> torch.Tensor:
        """Inputs for every member: ``x`` [B, T, W] (shared) repeated, or [M, B, T, W] (its own) as is."""
        return x.expand(self.cfg.members, *x.shape) if x.dim() == 3 else x

    def raw(self, params: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """Raw outputs ``[M, B, d_S, O]`` of the network with ``params`` on every member's own inputs
        ``x`` [M, B, T, W]: what the local graphs differentiate."""
        return ensemble_forward(params, x, self.cfg.heads)[0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Raw outputs ``[M, B, d_S, O]``: every member on ``x`` [B, T, W] (shared) or [M, B, T, W] (its own)."""
        return self.raw(self.params(), self.per_member(x))

    def attention_maps(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Self-attention weights ``[M, L, B, H, T, T]`` and output attention ``[M, B, H, d_S, T]`` on ``x`` [B, T, W]."""
        _, maps, out = ensemble_forward(self.params(), self.per_member(x), self.cfg.heads)
        return torch.stack(maps, dim=1), out

    @torch.no_grad()
    def prediction_nll(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        """The ensemble's prediction error: ``-log p(s' | s, a)`` summed over factors, averaged over
        members, ``[B]`` nats (what dynamics curiosity rewards)."""
        out = self(self.encode(state, action))
        return -self.log_likelihood(out, self.targets(state, next_state)).sum(dim=-1).mean(dim=0)

    def log_likelihood(self, out: torch.Tensor, targets: Targets) -> torch.Tensor:
        """``log p(s^j_{t+1})`` per output ``[..., d_S]`` of raw outputs ``[..., d_S, O]`` (soft labels: the
        expected log-probability, i.e. minus the cross-entropy)."""
        return torch.cat([self._categorical_log_probs(out, targets.labels)[0],
                          self._continuous(out, targets)[0]], dim=-1)[..., self.output_order]

    def probability(self, out: torch.Tensor, targets: Targets) -> torch.Tensor:
        """``p(s^j_{t+1})`` per output ``[..., d_S]``: the probability of the label (a soft label's
        expected probability), or the Normal density of the continuous value."""
        cat = self._categorical_log_probs(out, targets.labels)[1]
        return torch.cat([cat, self._continuous(out, targets)[0].exp()], dim=-1)[..., self.output_order]

    def graph_quantity(self, out: torch.Tensor, targets: Targets) -> torch.Tensor:
        """What eq. 5.1 differentiates (``cfg.graph_of``), ``[..., d_S]``."""
        if self.cfg.graph_of == "probability":
            return self.probability(out, targets)
        return self.log_likelihood(out, targets)

    def prediction_error(self, out: torch.Tensor, targets: Targets) -> torch.Tensor:
        """Per-output error ``[..., d_S]``: cross-entropy for a categorical factor, half the squared
        error of the mean (the NLL of a unit-variance Normal without its constant) for a continuous one."""
        cat = -self._categorical_log_probs(out, targets.labels)[0]
        return torch.cat([cat, self._continuous(out, targets)[1]], dim=-1)[..., self.output_order]

    def _categorical_log_probs(self, out: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        codec = self.codec
        if not codec.cat_factors:
            empty = out.new_zeros(out.shape[:-2] + (0,))
            return empty, empty
        logits = out[..., codec.cat_index, : codec.max_cat].masked_fill(~self.cat_class_mask, float("-inf"))
        logp = torch.log_softmax(logits, dim=-1).masked_fill(~self.cat_class_mask, 0.0)
        return (labels * logp).sum(-1), (labels * logp.exp()).sum(-1)

    def _continuous(self, out: torch.Tensor, targets: Targets) -> tuple[torch.Tensor, torch.Tensor]:
        """(log-density, half squared error of the mean) of the continuous factors ``[..., n_cont]``."""
        codec = self.codec
        if not codec.cont_factors:
            empty = out.new_zeros(out.shape[:-2] + (0,))
            return empty, empty
        m = codec.max_cont
        raw = out[..., codec.cont_index, :]
        log_std = raw[..., m : 2 * m].clamp(self.cfg.log_std_min, self.cfg.log_std_max)
        residual = targets.following - targets.current - raw[..., :m]
        per_dim = 0.5 * (residual * torch.exp(-log_std)).square() + log_std + 0.5 * LOG_2PI
        return -(per_dim * codec.cont_valid).sum(-1), (0.5 * residual.square() * codec.cont_valid).sum(-1)

    def predicted_classes(self, out: torch.Tensor) -> torch.Tensor:
        """Most likely next category of each categorical factor, ``[..., n_cat]``."""
        logits = out[..., self.codec.cat_index, : self.codec.max_cat]
        return logits.masked_fill(~self.cat_class_mask, float("-inf")).argmax(-1)

    def reduce_inputs(self, jacobian: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Partial derivatives w.r.t. every input entry ``[..., T, W]`` -> one per variable ``[..., T]``:
        a one-hot variable's gradient times its input, summed (the derivative along the observed
        category), in absolute value; a continuous variable's absolute gradients summed over its dimensions."""
        along = (jacobian * x).sum(-1).abs()
        total = (jacobian.abs() * self.input_valid).sum(-1)
        return torch.where(self.input_onehot, along, total)


def model_from_config(data: dict) -> ELDENModel:
    """An ELDENModel (untrained) from a parsed model configuration (``{"model": "elden", ...}``)."""
    if data.get("model") != "elden":
        raise ValueError(f"not an ELDEN model config: {data.get('model')!r}")
    return ELDENModel(layout_from_config(data), ELDENConfig(**data["elden"]))
