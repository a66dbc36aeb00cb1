"""CDL's max aggregation over inputs (ch. 3, Fig. 3.3) and its lean gradients.

Features are laid out ``[J, I, B, F]`` = (output factor, input, sample, feature). Eq. 3.3 needs three
aggregates of one feature tensor (every input, one input dropped, the causal parents); eq. 3.2 needs
every drop-one aggregate. All come from the top two values over inputs, and a gradient is routed to
the input(s) holding the max (ties have probability zero: features are linear outputs).
"""
from __future__ import annotations

import torch


def max_and_runner_up(feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Max over inputs (dim 1), the max without the arg-max input, and where the max sits.

    ``where(is_max[:, i], runner_up, first)`` is the aggregate with input i masked to -inf, for
    every i at once. Features are linear outputs, so exact ties have probability zero.
    """
    first = feats.amax(dim=1, keepdim=True)
    is_max = feats == first
    runner_up = torch.where(is_max, float("-inf"), feats).amax(dim=1, keepdim=True)
    return first, runner_up, is_max


def _indicator(x: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """1.0 where ``x == value`` (broadcast), else 0.0, in ``x``'s dtype. On the CPU a float mask
    multiplies at full vector speed where a bool one (``where``, ``masked_fill``, ``* bool``) runs ~3x
    slower over the [J, I, B, F] features, and it is made by the comparison itself, with no cast."""
    return torch.eq(x, value, out=torch.empty_like(x))


def _top_two(feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The largest and second-largest feature over inputs (dim 1), each [J, 1, B, F], by one running
    pass over the inputs: no full-size temporaries (with no ties, the second is the max without the
    arg-max input, as in :func:`max_and_runner_up`; with ties, the tied value).

    Each input x updates the pair by two operators: ``second = clamp(x, second, first)``, which is
    ``max(second, min(first, x))`` because second <= first, then ``first = max(first, x)``; written
    as min, then max, it took three, a temporary, and ~1.45x as long."""
    if feats.shape[1] == 1:
        return feats[:, :1].clone(), torch.full_like(feats[:, :1], float("-inf"))
    first = torch.maximum(feats[:, 0], feats[:, 1])
    second = torch.minimum(feats[:, 0], feats[:, 1])
    for i in range(2, feats.shape[1]):
        torch.clamp(feats[:, i], min=second, max=first, out=second)
        torch.maximum(first, feats[:, i], out=first)
    return first[:, None], second[:, None]


class _MaxAndDropOne(torch.autograd.Function):
    """(max over inputs, max over inputs without input ``drop``) with a lean backward.

    Autograd's ``amax`` backward normalises by tie counts in several passes over [J, I, B, F];
    ties have probability zero here, so the gradient is simply routed to the arg-max (and, for the
    dropped term, to the runner-up where the arg-max was dropped). The top two come from one running
    max/min (:func:`_top_two`) and the routing from float indicators: the only full-size tensors
    made are the two indicators forward and the gradient backward.
    """

    @staticmethod
    def forward(ctx, feats: torch.Tensor, drop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        first, runner_up = _top_two(feats)
        dropped_is_max = feats.gather(1, drop.expand(-1, -1, -1, feats.shape[-1])) == first
        dropped = torch.where(dropped_is_max, runner_up, first)
        ctx.save_for_backward(_indicator(feats, first), _indicator(feats, runner_up), dropped_is_max)
        return first, dropped

    @staticmethod
    def backward(ctx, grad_first: torch.Tensor, grad_dropped: torch.Tensor) -> tuple[torch.Tensor, None]:
        is_max, is_runner_up, dropped_is_max = ctx.saved_tensors
        to_max = grad_first + grad_dropped.masked_fill(dropped_is_max, 0.0)
        to_runner_up = grad_dropped.masked_fill(~dropped_is_max, 0.0)
        return torch.addcmul(is_max * to_max, is_runner_up, to_runner_up), None


class _MaskedMax(torch.autograd.Function):
    """Max over the inputs ``keep`` ([J, I] bool, group order) allows, gradient routed to the arg-max.

    Equal to ``feats.masked_fill(~keep, -inf).amax(1)`` and its autograd gradient (ties have
    probability zero), without a masked copy of the features or autograd's tie-counting backward:
    masked inputs get a -inf bias (an add, not a ``masked_fill``)."""

    @staticmethod
    def forward(ctx, feats: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        bias = torch.zeros(keep.shape, dtype=feats.dtype, device=feats.device).masked_fill_(~keep, float("-inf"))
        masked = feats + bias[:, :, None, None]
        out = masked.amax(dim=1, keepdim=True)
        ctx.save_for_backward(_indicator(masked, out))
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        (is_max,) = ctx.saved_tensors
        return is_max * grad, None


def masked_max(feats: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """Features [J, I, B, F] aggregated over the inputs ``keep`` [J, I] (group order) allows: [J, 1, B, F]."""
    return _MaskedMax.apply(feats, keep)


def _flat_rows(index: torch.Tensor, inputs: int) -> torch.Tensor:
    """Rows of a [J * I, ...] view for the inputs ``index`` [J, K] of each output: ``j * I + index[j, k]``."""
    return (torch.arange(index.shape[0], device=index.device)[:, None] * inputs + index).reshape(-1)


def _kept_inputs(feats: torch.Tensor, excluded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each output's kept (not ``excluded``) inputs' features: ``(index [J, K], features [J, K, B, F])``,
    K the most any output keeps; an output keeping fewer is padded with -inf features."""
    keep = ~excluded
    counts = keep.sum(dim=1)
    index = torch.argsort(keep.to(torch.uint8), dim=1, descending=True, stable=True)[:, : int(counts.max())]
    j, i = feats.shape[:2]
    # whole [B, F] blocks by one index_select over a [J * I] view: ~3x faster than ``gather`` with an
    # index expanded over B and F, which indexes element by element
    kept = feats.reshape(j * i, *feats.shape[2:]).index_select(0, _flat_rows(index, i))
    kept = kept.view(j, index.shape[1], *feats.shape[2:])
    padding = (torch.arange(index.shape[1], device=feats.device) >= counts[:, None]).view(-1).nonzero().squeeze(1)
    # only the padded [B, F] blocks are written (a masked_fill_ with a broadcast mask visits every element)
    kept.view(-1, kept[0, 0].numel()).index_fill_(0, padding, float("-inf"))
    return index, kept


class _TrainingAggregates(torch.autograd.Function):
    """Eq. 3.3's three aggregates of one feature tensor, the dropped and causal ones only on the rows
    where they differ from the full aggregate. See :func:`training_aggregates`."""

    @staticmethod
    def forward(ctx, feats: torch.Tensor, drop: torch.Tensor, excluded: torch.Tensor | None):
        first, second = (x[:, 0] for x in _top_two(feats))  # [J, B, F]
        j, i, b, f = feats.shape  # the dropped input's features: whole [F] rows of a [J * I * B, F] view
        rows = (_flat_rows(drop[:, 0, :, 0], i).view(j, b) * b + torch.arange(b, device=feats.device)).reshape(-1)
        dropped_is_max = feats.reshape(-1, f).index_select(0, rows).view(j, b, f) == first
        d_j, d_b = dropped_is_max.any(dim=-1).nonzero(as_tuple=True)
        d_rows = _sample_rows(d_j, d_b, first)
        rows_max = _take(dropped_is_max, d_rows)  # [Nd, F]: where the runner-up takes the dropped arg-max's place
        dropped = torch.where(rows_max, _take(second, d_rows), _take(first, d_rows))
        c_j = c_b = c_rows = d_j[:0]
        kept_rows, c_pairs, index, routes = first.new_zeros(0, first.shape[-1]), None, None, None
        if excluded is not None and bool(excluded.any()):
            index, features = _kept_inputs(feats, excluded)
            kept = features.amax(dim=1)
            # the causal max is routed on its own where it differs from the full one, and where two inputs
            # tie for the max (one of them may be excluded); elsewhere it is the full max, routed with it
            c_pairs = (kept != first) | (first == second)
            c_j, c_b = c_pairs.any(dim=-1).nonzero(as_tuple=True)
            c_rows = _sample_rows(c_j, c_b, first)
            kept_rows, routes = _take(kept, c_rows), _indicator(features, kept[:, None])
        ctx.mark_non_differentiable(d_j, d_b, c_j, c_b)
        ctx.save_for_backward(feats, first, second, rows_max, d_rows, c_pairs, c_rows, index, routes)
        return first, dropped, kept_rows, d_j, d_b, c_j, c_b

    @staticmethod
    def backward(ctx, g_first, g_dropped, g_kept, *_):
        feats, first, second, rows_max, d_rows, c_pairs, c_rows, index, routes = ctx.saved_tensors
        # [J, B, F]: what the arg-max of every (output, sample, feature) receives (contiguous: written by rows)
        to_max = g_first.clone(memory_format=torch.contiguous_format)
        if len(d_rows):
            _row_view(to_max).index_add_(0, d_rows, g_dropped.masked_fill(rows_max, 0.0))
        to_kept = None
        if len(c_rows):
            rows_own = _take(c_pairs, c_rows)
            _row_view(to_max).index_add_(0, c_rows, g_kept.masked_fill(rows_own, 0.0))
            to_kept = torch.zeros_like(to_max)
            _row_view(to_kept).index_copy_(0, c_rows, g_kept.masked_fill(~rows_own, 0.0))
        grad = _indicator(feats, first[:, None]).mul_(to_max[:, None])
        j, i, b, f = feats.shape
        row, p_f = rows_max.nonzero(as_tuple=True)  # the runner-up takes the dropped arg-max's place
        if len(row):
            cell = d_rows[row] * f + p_f  # (j, b, f) in a [J, B, F] tensor
            block = b * f  # then input 0's element (j, 0, b, f) of the features, and each input's a block further
            base = cell // block * (i * block) + cell % block
            # the P (output, sample, feature) columns over inputs by one index_select of single elements,
            # and the gradient added where they equal the runner-up (one element per column without ties):
            # an index_put_ of the whole [P, I] columns into a permuted view was ~4x slower
            at = base[:, None] + torch.arange(i, device=feats.device) * block
            column = feats.reshape(-1).index_select(0, at.view(-1)).view(-1, i)
            q, k = (column == second.reshape(-1)[cell][:, None]).nonzero(as_tuple=True)
            grad.view(-1).index_add_(0, base[q] + k * block, g_dropped[row[q], p_f[q]])
        if to_kept is not None:  # to the kept inputs holding the causal max; index_add_ of whole [B, F]
            # blocks: ~10x faster than scatter_add_ along dim 1
            grad.view(j * i, -1).index_add_(0, _flat_rows(index, i), (routes * to_kept[:, None]).reshape(index.numel(), -1))
        return grad, None, None


def _sample_rows(out_j: torch.Tensor, sample: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Row numbers ``j * B + b`` of (output, sample) pairs in :func:`_row_view` of a [J, B, F] tensor ``like``."""
    return out_j * like.shape[1] + sample


def _row_view(x: torch.Tensor) -> torch.Tensor:
    """A [J, B, F] tensor as [J * B, F] rows (a view), read and written by whole rows."""
    return x.view(-1, x.shape[-1])


def _take(x: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Rows ``rows`` (:func:`_sample_rows`) of a [J, B, F] tensor: [N, F], by one ``index_select`` of
    whole rows (advanced indexing with two index tensors is several times slower)."""
    return x.reshape(-1, x.shape[-1]).index_select(0, rows)


def training_aggregates(feats: torch.Tensor, drop: torch.Tensor, excluded: torch.Tensor | None
                        ) -> tuple[torch.Tensor, ...]:
    """Eq. 3.3's aggregates of features [J, I, B, F]: ``(first, dropped, kept, d_j, d_b, c_j, c_b)``.

    ``first`` [J, B, F] is the max over every input. Dropping input ``drop[j, 0, b, 0]`` changes row
    (j, b) only where that input holds the max of some feature; masking the inputs ``excluded`` [J, I]
    marks (the non-parents, group order; None: no causal term) changes it only where one of them
    does. Only those rows are returned: ``dropped`` [Nd, F] for rows (d_j, d_b), ``kept`` [Nc, F] for
    (c_j, c_b); every other row's dropped / causal aggregate *is* ``first``'s, so its prediction and
    loss are the full one's, and taking them from there gives the same loss and gradient as running
    the heads on every row (tests/causal/test_cdl.py). The gradient is routed as
    :class:`_MaxAndDropOne` and :class:`_MaskedMax` route it (to every input equal to the max) into
    one gradient tensor: one full-size indicator and product (the causal max is taken over each
    output's parents only), against their nine full-size passes and a sum of two gradients."""
    return _TrainingAggregates.apply(feats, drop, excluded)
