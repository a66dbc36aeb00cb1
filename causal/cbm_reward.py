"""CBM's causal reward model (dissertation ch. 4.2.1, Fig. 4.2 (a)): R(M (.) S_t, A_t).

One network predicts the reward from the factors and the action a binary mask M keeps: every factor's
encoding (one-hot colour, normalised values) and the action's are multiplied by their mask bit and,
with the mask itself (so a dropped input is told apart from a zero one), fed to an MLP giving a
Gaussian's mean and log standard deviation (clipped). Training maximises the likelihood under the
full mask and under *every* drop-one mask of each batch; the reward's CMI with input i is
``E[log R(S, A) / R(X^{-i})] = E[NLL(i dropped) - NLL(full)]`` in nats, and S^i is a parent of the
reward when it is at least the reward threshold (0.01). Assumption 7 (factors affect the reward
independently) is what makes one drop-one test per factor enough.

Why an MLP over the masked inputs and not CDL's per-input features with a max: a task reward reads
factors *together* (Match compares each colour with its goal colour), which a max over features of
one input each represents poorly; measured on chemical-distractors (3 objects), the max-aggregated
model had not found two of the three colours after 3,000 updates (docs/results.md).

Rewards are modelled in their own units: the tasks here give rewards of order 1, well inside what the
log-std clip [-6, 2] can express.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from causal.cbm_config import CBMConfig
from causal.cbm_nets import constant_inputs
from causal.factored import FactorCodec, FactorLayout
from causal.rl.networks import mlp

HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


class CausalRewardModel(nn.Module):
    """``R(M (.) S, A)``: a Gaussian reward predictor conditioned on any input mask."""

    def __init__(self, layout: FactorLayout, cfg: CBMConfig) -> None:
        super().__init__()
        self.layout, self.cfg, self.codec = layout, cfg, FactorCodec(layout)
        n = layout.num_factors
        width = n * layout.input_width + layout.action_width + n + 1
        self.net = mlp(width, (cfg.reward_hidden, cfg.reward_hidden), 2)
        masks = torch.ones(n + 2, n + 1)
        masks[torch.arange(1, n + 2), torch.arange(n + 1)] = 0.0
        self.register_buffer("masks", masks)
        """Row 0 keeps every input; row 1 + i drops input i (factors in order, then the action)."""

    def outputs(self, state: torch.Tensor, action: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
        """``[M, B, 2]`` (mean, log std) of the reward under each of the ``masks`` ``[M, d_S + 1]``."""
        n, b = self.layout.num_factors, state.shape[0]
        factors = self.codec.encode_state(state.to(torch.float32))[None] * masks[:, None, :n, None]
        act = self.codec.encode_action(action)[None] * masks[:, None, n:]
        bits = masks[:, None, :].expand(-1, b, -1)
        return self.net(torch.cat([factors.flatten(2), act, bits], dim=-1))

    def nll_all_masks(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        """Gaussian NLL ``[1 + I, B]`` of the rewards under the full mask, then each drop-one mask, nats."""
        out = self.outputs(state, action, self.masks)
        log_std = out[..., 1].clamp(self.cfg.log_std_min, self.cfg.log_std_max)
        z = (reward.reshape(1, -1).to(out.dtype) - out[..., 0]) * torch.exp(-log_std)
        return 0.5 * z.square() + log_std + HALF_LOG_2PI

    @torch.no_grad()
    def cmi(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor, chunk: int = 1024,
            zero_constant_inputs: bool = True) -> torch.Tensor:
        """Reward CMI of every input ``[I]`` (factors, then the action), nats. Inputs constant over the
        samples get 0 (a constant carries no information)."""
        total = torch.zeros(self.layout.num_factors + 1)
        for start in range(0, state.shape[0], chunk):
            nll = self.nll_all_masks(*(t[start : start + chunk] for t in (state, action, reward)))
            total += (nll[1:] - nll[:1]).sum(dim=1)
        cmi = total / max(state.shape[0], 1)
        if zero_constant_inputs and state.shape[0]:
            cmi[constant_inputs(self.layout, state, action)] = 0.0
        return cmi

    @torch.no_grad()
    def predict(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The full model's predicted reward (the Gaussian's mean) ``[B]``."""
        return self.outputs(state, action, self.masks[:1])[0, :, 0]
