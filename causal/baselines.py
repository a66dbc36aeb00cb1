"""The dense dynamics baselines of ch. 3.3.2, with parameter counts matched to a CDL model.

- ``Modular``: one network per state factor (Ke et al., 2021), i.e. CDL's own architecture with no
  feature masked. It *is* a :class:`CDLModel` always used in full mode, so its parameter count
  equals CDL's exactly.
- ``Monolithic``: one MLP from all state factors and the action to the next-step distributions of
  all factors, the usual MBRL model; its width is chosen so that its parameter count is as close
  as possible to CDL's ("we try our best to give them the same number of parameters").

Both predict in CDL's output format (``[d_S, B, head_width]``: colour logits, Normal mean residual
and log-std) and score it with CDL's likelihood, so every evaluation treats all three alike.
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import nn

from causal.cdl import CDLConfig, CDLModel
from causal.factored import FactorCodec, FactorLayout
from causal.planning import StepFn, next_state_from_outputs
from causal.rl.networks import mlp


class MonolithicModel(nn.Module):
    """One MLP (``depth`` hidden layers of ``width``) from all inputs to all next-factor distributions."""

    # CDL's likelihood (with the targets and scoring it is made of) and class mask read only ``codec``,
    # ``layout``, ``cfg`` and ``cat_class_mask``, which this model holds too: borrowing them keeps one
    # definition of the output format.
    _likelihood = CDLModel.nll
    _targets = CDLModel._targets
    _nll_of = CDLModel._nll_of
    _class_mask = CDLModel._class_mask

    def __init__(self, layout: FactorLayout, width: int, depth: int = 3, cfg: CDLConfig = CDLConfig()) -> None:
        super().__init__()
        self.layout, self.cfg, self.width, self.depth = layout, cfg, width, depth
        self.codec = FactorCodec(layout)
        self.register_buffer("cat_class_mask", self._class_mask())
        inputs = layout.num_factors * layout.input_width + layout.action_width
        self.net = mlp(inputs, [width] * depth, layout.num_factors * layout.head_width)

    def outputs(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x = torch.cat([self.codec.encode_state(state).flatten(1), self.codec.encode_action(action)], dim=1)
        return self.net(x).view(state.shape[0], self.layout.num_factors, -1).transpose(0, 1)

    def nll(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        return self._likelihood(self.outputs(state, action)[:, None], state, next_state)[:, 0]


class ModularModel(nn.Module):
    """CDL's architecture with no masking: a :class:`CDLModel` always used in full mode."""

    def __init__(self, layout: FactorLayout, cfg: CDLConfig = CDLConfig()) -> None:
        super().__init__()
        self.model = CDLModel(layout, cfg)
        self.layout, self.cfg, self.codec = layout, cfg, self.model.codec

    def outputs(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        aggregated = self.model.features(state, action).amax(dim=1, keepdim=True)
        return self.model.predict(aggregated)[:, 0]

    def nll(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        return self.model.nll(self.outputs(state, action)[:, None], state, next_state)[:, 0]


DenseDynamics = MonolithicModel | ModularModel
"""A dynamics model that always uses every input."""


def parameter_count(module: nn.Module) -> int:
    """Number of trainable scalars."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def match_parameter_count(target: int, builder: Callable[[int], nn.Module], low: int = 1, high: int = 1 << 14) -> int:
    """The width in ``[low, high]`` whose ``builder(width)`` has the parameter count closest to
    ``target`` (counts must grow with width)."""
    lo, hi = low, low
    while hi < high and parameter_count(builder(hi)) < target:  # doubling first: never build a huge model
        lo, hi = hi + 1, min(2 * hi, high)
    while lo < hi:  # then the smallest width reaching the target
        mid = (lo + hi) // 2
        if parameter_count(builder(mid)) < target:
            lo = mid + 1
        else:
            hi = mid
    candidates = [w for w in (lo - 1, lo) if w >= low]
    return min(candidates, key=lambda w: abs(parameter_count(builder(w)) - target))


def matched_monolithic(model: CDLModel, depth: int = 3) -> MonolithicModel:
    """A Monolithic baseline with (about) as many parameters as ``model``."""
    target = parameter_count(model)
    width = match_parameter_count(target, lambda w: MonolithicModel(model.layout, w, depth, model.cfg))
    return MonolithicModel(model.layout, width, depth, model.cfg)


class DenseDynamicsTrainer:
    """Maximum likelihood for a dense baseline: Adam on the summed per-factor mean NLL."""

    def __init__(self, model: DenseDynamics, lr: float | None = None, seed: int = 0) -> None:
        torch.manual_seed(seed)
        self.model = model
        self.optimizer = torch.optim.Adam(model.parameters(), lr=model.cfg.lr if lr is None else lr, fused=True)
        self.updates = 0

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        """One gradient step; returns the mean NLL per factor (nats) before it."""
        nll = self.model.nll(state, action, next_state)
        loss = nll.mean(dim=1).sum()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.model.parameters(), self.model.cfg.grad_clip)
        self.optimizer.step()
        self.updates += 1
        return {"nll_full": nll.detach().mean().item()}


def dense_rollout_step(model: DenseDynamics, sample: bool = False, generator: torch.Generator | None = None) -> StepFn:
    """``step_fn`` (for planning or k-step evaluation) from a dense baseline."""
    log_std_range = (model.cfg.log_std_min, model.cfg.log_std_max)

    @torch.no_grad()
    def step(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        out = model.outputs(states, actions)
        return next_state_from_outputs(model.codec, out, states, sample, generator, log_std_range, model.cfg.target)

    return step
