"""CBM's causal reward model (dissertation ch. 4.2.1, Fig. 4.2 (a)): R(M (.) S_t, A_t).

One network predicts the reward from the factors and the action a binary mask M keeps: every factor's
encoding (one-hot colour, normalised values) and the action's are multiplied by their mask bit and,
with the mask itself (so a dropped input is told apart from a zero one), fed to an MLP giving the
reward's mean. Training minimises the squared error under the full mask and under *every* drop-one
mask of each batch.

The predictive distribution is Gaussian with one variance per mask, its maximum-likelihood value on the
data it is evaluated on (the mask's mean squared error). The reward's CMI with input i,
``E[log R(S, A) / R(X^{-i})]``, is then ``0.5 log(MSE(i dropped) / MSE(full))`` in nats, and S^i is a
parent of the reward when it is at least the reward threshold (0.01). Assumption 7 (factors affect
the reward independently) is what makes one drop-one test per factor enough. A variance per sample
(a heteroscedastic head) was tried first: its held-out likelihood ratios swung by up to 0.1 nats for
inputs the reward ignores, because a network that grows overconfident on its training data is
penalised on held-out data by an amount that varies from mask to mask (docs/deviations.md).

Why an MLP over the masked inputs and not CDL's per-input features with a max: a task reward reads
factors *together* (Match compares each colour with its goal colour), which a max over features of
one input each represents poorly; the max-aggregated model had found one of the three colours of
chemical-distractors after 3,000 updates.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from causal.cbm_config import CBMConfig
from causal.cbm_nets import constant_inputs
from causal.factored import FactorCodec, FactorLayout
from causal.rl.networks import mlp

HALF_LOG_2PI_E = 0.5 * math.log(2 * math.pi * math.e)


class CausalRewardModel(nn.Module):
    """``R(M (.) S, A)``: a Gaussian reward predictor conditioned on any input mask."""

    def __init__(self, layout: FactorLayout, cfg: CBMConfig) -> None:
        super().__init__()
        self.layout, self.cfg, self.codec = layout, cfg, FactorCodec(layout)
        n = layout.num_factors
        width = n * layout.input_width + layout.action_width + n + 1
        self.net = mlp(width, (cfg.reward_hidden, cfg.reward_hidden), 1)
        masks = torch.ones(n + 2, n + 1)
        masks[torch.arange(1, n + 2), torch.arange(n + 1)] = 0.0
        self.register_buffer("masks", masks)
        """Row 0 keeps every input; row 1 + i drops input i (factors in order, then the action)."""

    def means(self, state: torch.Tensor, action: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
        """``[M, B]`` predicted rewards under each of the ``masks`` ``[M, d_S + 1]``."""
        n, b = self.layout.num_factors, state.shape[0]
        factors = self.codec.encode_state(state.to(torch.float32))[None] * masks[:, None, :n, None]
        act = self.codec.encode_action(action)[None] * masks[:, None, n:]
        bits = masks[:, None, :].expand(-1, b, -1)
        return self.net(torch.cat([factors.flatten(2), act, bits], dim=-1))[..., 0]

    def squared_errors(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
        """``[1 + I, B]`` squared errors under the full mask, then each drop-one mask (the training loss)."""
        return (self.means(state, action, self.masks) - reward.reshape(1, -1).to(torch.float32)).square()

    @torch.no_grad()
    def cmi(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor, chunk: int = 1024,
            zero_constant_inputs: bool = True) -> torch.Tensor:
        """Reward CMI of every input ``[I]`` (factors, then the action), nats: ``0.5 log(MSE_{-i} / MSE)``.
        Inputs constant over the samples get 0 (a constant carries no information), and every input
        gets 0 when the reward itself is constant (nothing to explain)."""
        return self.cmi_with_stderr(state, action, reward, chunk, zero_constant_inputs)[0]

    @torch.no_grad()
    def cmi_with_stderr(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor, chunk: int = 1024,
                        zero_constant_inputs: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`cmi` and its standard error ``[I]`` over the samples, by the delta method: the CMI is
        a function of two means of per-sample squared errors (full ``e0``, input ``i`` dropped ``ei``),
        whose per-sample influence is ``0.5 (ei / mean(ei) - e0 / mean(e0))``; the standard error is
        that term's spread over ``sqrt(n)``. Zero wherever :meth:`cmi` is set to 0."""
        n_inputs = self.layout.num_factors + 1
        sums = torch.zeros(n_inputs + 1, dtype=torch.float64)
        squares = torch.zeros_like(sums)
        cross = torch.zeros(n_inputs, dtype=torch.float64)
        for start in range(0, state.shape[0], chunk):
            errors = self.squared_errors(*(t[start : start + chunk] for t in (state, action, reward))).double()
            sums += errors.sum(dim=1)
            squares += errors.square().sum(dim=1)
            cross += (errors[1:] * errors[:1]).sum(dim=1)
        n = state.shape[0]
        spread = float(reward.to(torch.float64).var()) if reward.numel() > 1 else 0.0
        if spread <= 0.0:
            return torch.zeros(n_inputs), torch.zeros(n_inputs)
        mse = sums / n + 1e-9 * spread  # floor: a reward fitted exactly stays finite
        cmi = (0.5 * torch.log(mse[1:] / mse[:1])).to(torch.float32)
        variance = (squares / n - (sums / n).square()).clamp_min(0.0)
        covariance = cross / n - sums[1:] * sums[:1] / n**2
        influence = 0.25 * (variance[1:] / mse[1:] ** 2 + variance[:1] / mse[:1] ** 2
                            - 2 * covariance / (mse[1:] * mse[:1]))
        stderr = (influence.clamp_min(0.0) * n / max(n - 1, 1) / n).sqrt().to(torch.float32)
        if zero_constant_inputs:
            constant = constant_inputs(self.layout, state, action)
            cmi[constant], stderr[constant] = 0.0, 0.0
        return cmi, stderr

    @staticmethod
    def nll(squared_errors: torch.Tensor) -> torch.Tensor:
        """Per-mask Gaussian NLL per sample, nats, with each mask's maximum-likelihood variance: ``[1 + I]``."""
        return 0.5 * torch.log(squared_errors.mean(dim=-1) + 1e-12) + HALF_LOG_2PI_E

    @torch.no_grad()
    def predict(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The full model's predicted reward ``[B]``."""
        return self.means(state, action, self.masks[:1])[0]
