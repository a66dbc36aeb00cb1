"""CBM's implicit dynamics (dissertation ch. 4.2.2): energies, InfoNCE with regularisers, CMI, argmax.

For every next factor j the energy is ``f(s, a, c) = <enc(M (.) (s, a))_j, enc_j(c)>``, where c is a
candidate value of ``s^j_{t+1}``: the change ``delta s_j`` (normalised) for a continuous factor, the
category for a categorical one. With ``CBMConfig.target = "next"`` a continuous factor's candidate is
its next value itself (eq. 4.1's label) and its "delta range" is that of the next values: the change
needs the factor's own value at t, which redundant inputs can stand in for (docs/methods/cbm.md).
``"auto"`` chooses per factor, from the first batch, whichever of the two varies less.

``enc(s, a)`` is the masked network of :mod:`causal.cbm_nets`, so the full model f_impl (all inputs),
every drop-one model psi^i (input i masked) and the causal model (learned parents) share one network
and one feature computation (the text's "same masking technique [...] to combine f_impl and psi into
one network").

Training (Algorithm 3, eqs. 4.1, 4.4, 4.5): InfoNCE of the label against N negatives drawn uniformly
over the factor's delta range (Latin hypercube: stratified, so marginally uniform), plus
``lambda1 f(c)^2 + lambda2 ||df/dc||^2`` summed over the label and every negative, for f_impl
and for psi (one random dropped input per output and sample, as CDL trains its masked term); the
causal-parents term every ``causal_every`` updates. A categorical factor's candidates are all its
categories, so its InfoNCE is the cross-entropy of a softmax over them (no gradient penalty).

CMI (Algorithm 4, eq. 4.3): phi = f_impl - psi^i and self-normalised weights w = softmax(psi^i) over
the negatives. Because ``log w_n + phi_n = f_n - logsumexp(psi^i)``, the weighted sum is
``N * sum_n exp(f_n) / sum_n exp(psi^i_n)``: two log-sum-exps per (output, mask, sample), streamed
over chunks of negatives. For a categorical factor the candidates enumerate the support, where eq.
4.3 tends (N -> infinity) to ``log softmax f(label) - log softmax psi^i(label)``, which is used.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from causal.cbm_config import CBMConfig
from causal.cbm_nets import MaskedFeatures, StackedMLP, constant_inputs, masked_max, stacked
from causal.cdl import _MaxAndDropOne, max_and_runner_up  # CDL's top-2 max: every drop-one mask in one pass
from causal.factored import FactorLayout

CHUNK_ELEMENTS = 1 << 23
"""Energies held at once by a CMI estimate (32 MiB of float32): bounds its memory on any layout."""


def importance_weighted_cmi(f_label: torch.Tensor, f_neg: torch.Tensor, psi_label: torch.Tensor,
                            psi_neg: torch.Tensor) -> torch.Tensor:
    """Eq. 4.3 for each sample: ``log (N+1) e^phi(label) / (e^phi(label) + N sum_n w_n e^phi(n))`` with
    ``phi = f - psi`` and ``w = softmax(psi(negatives))``. Scores of the negatives are ``[..., N]``."""
    n = f_neg.shape[-1]
    phi, log_w = f_label - psi_label, torch.log_softmax(psi_neg, dim=-1)
    weighted = math.log(n) + torch.logsumexp(log_w + f_neg - psi_neg, dim=-1)
    return math.log(n + 1) + phi - torch.logaddexp(phi, weighted)


def cmi_from_sums(phi_label: torch.Tensor, lse_f: torch.Tensor, lse_psi: torch.Tensor, n: int) -> torch.Tensor:
    """:func:`importance_weighted_cmi` from ``logsumexp`` of f and psi over the negatives (streamable)."""
    return math.log(n + 1) + phi_label - torch.logaddexp(phi_label, math.log(n) + lse_f - lse_psi)


class ImplicitDynamics(nn.Module):
    """The d_S implicit models f^{impl, j} as one batched, masked module."""

    def __init__(self, layout: FactorLayout, cfg: CBMConfig) -> None:
        super().__init__()
        self.layout, self.cfg = layout, cfg
        n, e = layout.num_factors, cfg.embed_dim
        self.features = MaskedFeatures(layout, n, cfg.feature_hidden, cfg.feature_dim)
        self.head = StackedMLP(n, (cfg.feature_dim, cfg.predictor_hidden, cfg.predictor_hidden, e))
        codec = self.codec = self.features.codec
        jc, jk, d, h = len(codec.cont_factors), len(codec.cat_factors), codec.max_cont, cfg.candidate_hidden
        if jc:
            self.cand_w1, self.cand_b1 = stacked(jc, d, h, fan_in=d), stacked(jc, 1, h, fan_in=d)
            self.cand_w2, self.cand_b2 = stacked(jc, h, e, fan_in=h), stacked(jc, 1, e, fan_in=h)
            # The delta range travels with the weights (parameters, never trained), so a model rebuilt
            # from published weights draws its negatives from the same range.
            self.delta_low = nn.Parameter(torch.zeros(jc, d), requires_grad=False)
            self.delta_high = nn.Parameter(torch.zeros(jc, d), requires_grad=False)
            if cfg.target == "auto":  # chosen per factor from the first batch, travels with the weights
                self.label_is_next = nn.Parameter(torch.zeros(jc), requires_grad=False)
        if jk:
            self.class_codes = stacked(jk, codec.max_cat, e, fan_in=e)
            valid = torch.zeros(jk, codec.max_cat, dtype=torch.bool)
            for row, j in enumerate(codec.cat_factors):
                valid[row, : layout.sizes[j]] = True
            self.register_buffer("class_valid", valid)

    # ---------------------------------------------------------------- candidates

    def label_deltas(self, state: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        """``[Jc, B, D]`` labels of the continuous factors (zero in padded dimensions): their normalised
        changes, or with ``target = "next"`` their normalised next values (the candidates' "delta range"
        is then the next values' range); ``"auto"``: each factor's as :meth:`choose_labels` chose."""
        return (self.codec.continuous_values(next_state) - self._label_origin(state)).permute(1, 0, 2)

    def _label_origin(self, state: torch.Tensor) -> torch.Tensor | float:
        """``[B, Jc, D]`` what each label is measured from: the factor's value at t for a change, 0 for a
        next value (a label plus its origin is the next value; with next values alone, the scalar 0)."""
        if self.cfg.target == "next":
            return 0.0
        current = self.codec.continuous_values(state)
        if self.cfg.target == "auto":
            return (1.0 - self.label_is_next)[None, :, None] * current
        return current

    @torch.no_grad()
    def observe_labels(self, state: torch.Tensor, next_state: torch.Tensor, first: bool) -> None:
        """Widen the label range to cover this batch's labels; on the ``first`` batch, with
        ``target = "auto"``, choose each factor's label first (:meth:`choose_labels`)."""
        if first and self.cfg.target == "auto":
            self.choose_labels(state, next_state)
        self.observe_deltas(self.label_deltas(state, next_state), first)

    @torch.no_grad()
    def choose_labels(self, state: torch.Tensor, next_state: torch.Tensor) -> None:
        """``target = "auto"``: each continuous factor's label from these transitions (the first batch), its
        next value where that varies less than its change does, else its change. A factor that persists
        (a position) changes by less than it varies; one that is overwritten every step (a controllable
        distractor, ``cd' = P a``) changes by more, about twice the variance when successive values are
        independent. Ties (a factor constant here) keep the change."""
        current, following = self.codec.continuous_values(state), self.codec.continuous_values(next_state)
        spread_next = following.var(dim=0, unbiased=False).sum(-1)
        spread_change = (following - current).var(dim=0, unbiased=False).sum(-1)
        self.label_is_next.copy_((spread_next < spread_change).to(self.label_is_next.dtype))

    @torch.no_grad()
    def observe_deltas(self, deltas: torch.Tensor, first: bool) -> None:
        """Widen the delta range to cover ``deltas`` ``[Jc, B, D]`` (``first``: set it to theirs); values that
        are not finite are left out (a batch of them takes no step, and must not spoil the range either)."""
        finite = torch.isfinite(deltas)
        low = deltas.masked_fill(~finite, float("inf")).amin(dim=1).nan_to_num(posinf=0.0)
        high = deltas.masked_fill(~finite, float("-inf")).amax(dim=1).nan_to_num(neginf=0.0)
        self.delta_low.copy_(low if first else torch.minimum(self.delta_low, low))
        self.delta_high.copy_(high if first else torch.maximum(self.delta_high, high))

    def negatives(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``[Jc, n, D]`` candidates uniform over the delta range: a Latin hypercube (one draw per
        stratum of every dimension, strata paired at random), so each is marginally uniform."""
        jc, d = self.delta_low.shape
        ranks = torch.argsort(torch.rand(jc, n, d, generator=generator), dim=1)
        u = (ranks + torch.rand(jc, n, d, generator=generator)) / n
        return self.delta_low[:, None] + u * (self.delta_high - self.delta_low)[:, None]

    def codes(self, deltas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """enc_j of candidates ``[Jc, M, D]`` -> codes ``[Jc, M, E]`` and the hidden units that are on."""
        pre = torch.baddbmm(self.cand_b1, deltas, self.cand_w1)
        return torch.baddbmm(self.cand_b2, torch.relu(pre), self.cand_w2), pre > 0

    # ---------------------------------------------------------------- scores

    def embeddings(self, aggregated: torch.Tensor) -> torch.Tensor:
        """enc(s, a)_j of aggregated features ``[J, K, B, F]`` -> ``[J, K, B, E]``."""
        return self.head(aggregated)

    def label_scores(self, u: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        """Energies of each sample's own candidate: embeddings ``[Jc, K, B, E]``, codes ``[Jc, B, E]``
        -> ``[Jc, K, B]``."""
        return (u * codes[:, None]).sum(-1)

    def shared_scores(self, u: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        """Energies of candidates shared by all samples: codes ``[Jc, M, E]`` -> ``[Jc, K, B, M]``."""
        jc, k, b, e = u.shape
        return torch.bmm(u.reshape(jc, k * b, e), codes.transpose(1, 2)).view(jc, k, b, -1)

    def candidate_grad_sq(self, u: torch.Tensor, on_label: torch.Tensor, on_neg: torch.Tensor) -> torch.Tensor:
        """``sum_c ||df(c)/dc||^2`` over each sample's label and the shared negatives, ``[Jc, K, B]``, in
        closed form (``f = <u, W2 relu(W1 c + b1) + b2>``): ``df/dc = W1 (on(c) * W2^T u)``; ``on_*`` are
        the candidates' active hidden units (:meth:`codes`)."""
        jc, k, b, _ = u.shape
        w1 = self.cand_w1 * self.codec.cont_valid[:, :, None]  # padded dimensions are no candidate's entries
        a = torch.bmm(u.reshape(jc, k * b, -1), self.cand_w2.transpose(1, 2))  # [Jc, K*B, H]
        g_label = torch.einsum("jkbh,jdh->jkbd", a.view(jc, k, b, -1) * on_label[:, None], w1)
        n, d = on_neg.shape[1], w1.shape[1]
        through = (on_neg[:, :, None, :] * w1[:, None]).reshape(jc, n * d, -1)
        g_neg = torch.bmm(a, through.transpose(1, 2)).view(jc, k, b, n, d)
        return g_label.square().sum(-1) + g_neg.square().sum((-1, -2))

    def class_logits(self, u: torch.Tensor) -> torch.Tensor:
        """Energies of every category of the categorical outputs ``[Jk, K, B, C]`` (invalid ones -inf)."""
        logits = torch.einsum("jkbe,jce->jkbc", u, self.class_codes)
        return logits.masked_fill(~self.class_valid[:, None, None, :], float("-inf"))

    # ---------------------------------------------------------------- training

    def training_losses(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                        parents: torch.Tensor | None, generator: torch.Generator | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """InfoNCE and regulariser ``[J, K, B]`` of eq. 4.5 for K = full, one random dropped input, and
        (when ``parents`` is given) the causal parents."""
        feats = self.features(state, action)
        j, i, b, _ = feats.shape
        drop = torch.randint(0, i, (j, 1, b, 1), generator=generator)
        terms = list(_MaxAndDropOne.apply(feats, drop))
        if parents is not None:
            terms.append(masked_max(feats, self.features.to_group_order(parents)))
        u = self.embeddings(torch.cat(terms, dim=1))
        nce, reg = u.new_empty(u.shape[:3]), u.new_empty(u.shape[:3])
        if self.codec.cont_factors:
            nce[self.codec.cont_index], reg[self.codec.cont_index] = self._cont_losses(
                u[self.codec.cont_index], self.label_deltas(state, next_state), generator)
        if self.codec.cat_factors:
            nce[self.codec.cat_index], reg[self.codec.cat_index] = self._cat_losses(
                u[self.codec.cat_index], next_state)
        return nce, reg

    def _cont_losses(self, u: torch.Tensor, label: torch.Tensor,
                     generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor]:
        v_label, on_label = self.codes(label)
        v_neg, on_neg = self.codes(self.negatives(self.cfg.num_negatives, generator))
        f_label, f_neg = self.label_scores(u, v_label), self.shared_scores(u, v_neg)
        nce = torch.logsumexp(torch.cat([f_label[..., None], f_neg], dim=-1), dim=-1) - f_label
        scores_sq = f_label.square() + f_neg.square().sum(-1)
        return nce, self.cfg.score_l2 * scores_sq + self.cfg.grad_l2 * self.candidate_grad_sq(u, on_label, on_neg)

    def _cat_losses(self, u: torch.Tensor, next_state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits = self.class_logits(u)
        label = self.codec.categories(next_state).T.clamp_max(self.codec.max_cat - 1)  # [Jk, B]
        index = label[:, None, :, None].expand(-1, u.shape[1], -1, 1)
        nce = -torch.log_softmax(logits, dim=-1).gather(-1, index).squeeze(-1)
        scores_sq = torch.where(self.class_valid[:, None, None, :], logits, 0.0).square().sum(-1)
        return nce, self.cfg.score_l2 * scores_sq

    # ---------------------------------------------------------------- CMI

    @torch.no_grad()
    def cmi(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor, num_negatives: int,
            generator: torch.Generator | None = None, zero_constant_inputs: bool = True) -> torch.Tensor:
        """CMI^{ij} of every output j and input i (eq. 4.3), averaged over the samples: ``[J, I]`` nats,
        graph column order. Inputs constant over the samples get 0 (as :meth:`CDLModel.cmi`)."""
        total, _ = self.cmi_sums(state, action, next_state, num_negatives, generator, zero_constant_inputs)
        return (total / max(state.shape[0], 1)).to(torch.float32)

    @torch.no_grad()
    def cmi_sums(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor, num_negatives: int,
                 generator: torch.Generator | None = None,
                 zero_constant_inputs: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """The sums over the samples of eq. 4.3's per-sample terms and of their squares, ``[J, I]`` float64,
        graph column order (their mean is :meth:`cmi`; with the squares, its standard error over the
        transitions, the negatives held fixed). Constant inputs get 0 in both."""
        j, i = self.layout.num_factors, self.layout.num_factors + 1
        negatives = self.negatives(num_negatives, generator) if self.codec.cont_factors else None
        chunk = max(1, CHUNK_ELEMENTS // (j * (i + 1) * min(num_negatives, 1024)))
        total = torch.zeros(j, i, dtype=torch.float64)
        squares = torch.zeros_like(total)
        for start in range(0, state.shape[0], chunk):
            s, a, n = (t[start : start + chunk] for t in (state, action, next_state))
            terms = self._cmi_terms(s, a, n, negatives).double().cpu()
            total += terms.sum(-1)
            squares += terms.square().sum(-1)
        total, squares = self.features.to_graph_order(total), self.features.to_graph_order(squares)
        if zero_constant_inputs and state.shape[0]:
            constant = constant_inputs(self.layout, state, action).cpu()
            total[:, constant], squares[:, constant] = 0.0, 0.0
        return total, squares

    def _cmi_terms(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                   negatives: torch.Tensor | None) -> torch.Tensor:
        """Eq. 4.3's term of every (output, input) and sample, group order ``[J, I, B]``."""
        first, runner_up, is_max = max_and_runner_up(self.features(state, action))
        u = self.embeddings(torch.cat([first, torch.where(is_max, runner_up, first)], dim=1))  # [J, 1+I, B, E]
        out = u.new_zeros(u.shape[0], u.shape[1] - 1, u.shape[2])
        codec = self.codec
        if codec.cont_factors:
            u_c = u[codec.cont_index]
            f_label = self.label_scores(u_c, self.codes(self.label_deltas(state, next_state))[0])
            lse = self._negatives_logsumexp(u_c, negatives)
            phi = f_label[:, :1] - f_label[:, 1:]
            out[codec.cont_index] = cmi_from_sums(phi, lse[:, :1], lse[:, 1:], negatives.shape[1])
        if codec.cat_factors:
            logits = self.class_logits(u[codec.cat_index])
            label = codec.categories(next_state).T.clamp_max(codec.max_cat - 1)
            index = label[:, None, :, None].expand(-1, logits.shape[1], -1, 1)
            logp = torch.log_softmax(logits, dim=-1).gather(-1, index).squeeze(-1)
            out[codec.cat_index] = logp[:, :1] - logp[:, 1:]
        return out

    def _negatives_logsumexp(self, u: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        """``logsumexp`` over the negatives of the energies ``[Jc, K, B]``, in chunks of 1,024 negatives."""
        lse = None
        for start in range(0, negatives.shape[1], 1024):
            part = torch.logsumexp(self.shared_scores(u, self.codes(negatives[:, start : start + 1024])[0]), dim=-1)
            lse = part if lse is None else torch.logaddexp(lse, part)
        return lse

    # ---------------------------------------------------------------- prediction

    @torch.no_grad()
    def predict(self, state: torch.Tensor, action: torch.Tensor, mask: torch.Tensor | None = None,
                num_candidates: int | None = None, generator: torch.Generator | None = None) -> torch.Tensor:
        """The next state ``argmax_c f(c; s, a)`` per factor (inputs restricted to ``mask`` ``[J, I]``, graph
        order, when given): the best of ``num_candidates`` uniform deltas, or of every category."""
        j, i = self.layout.num_factors, self.layout.num_factors + 1
        keep = torch.ones(j, i, dtype=torch.bool) if mask is None else self.features.to_group_order(mask.to(torch.bool))
        u = self.embeddings(masked_max(self.features(state, action), keep))
        out, codec = state.to(torch.float32).clone(), self.codec
        if codec.cont_factors:
            candidates = self.negatives(num_candidates or self.cfg.eval_negatives, generator)
            best = self.shared_scores(u[codec.cont_index], self.codes(candidates)[0])[:, 0].argmax(-1)  # [Jc, B]
            delta = candidates.gather(1, best[..., None].expand(-1, -1, candidates.shape[-1]))
            values = self._label_origin(state) + delta.permute(1, 0, 2)
            raw = values * codec.cont_scale[None, :, None] + codec.cont_loc[None, :, None]
            rows = torch.arange(state.shape[0])[:, None]
            for n in range(len(codec.cont_factors)):
                width = int(codec.cont_valid[n].sum())
                out[rows, codec.cont_cols[n, :width]] = raw[:, n, :width]
        if codec.cat_factors:
            out[:, codec.cat_cols] = self.class_logits(u[codec.cat_index])[:, 0].argmax(-1).T.to(out.dtype)
        return out
