"""CBM's causal reward model (dissertation ch. 4.2.1, Fig. 4.2 (a)): R(M (.) S_t, A_t).

One network predicts the reward from the factors and the action a binary mask M keeps: every factor's
encoding (one-hot colour, normalised values) and the action's are multiplied by their mask bit and,
with the mask itself (so a dropped input is told apart from a zero one), fed to an MLP giving the
reward's mean. Training minimises the squared error under the full mask and under *every* drop-one
mask of each batch.

The predictive distribution is Gaussian with one variance shared by every mask: the reward's variance
on the data it is evaluated on, ``Var(r)``. The reward's CMI with input i, ``E[log R(S, A) / R(X^{-i})]``,
is then ``(MSE(i dropped) - MSE(full)) / (2 Var(r))`` in nats: half the share of the reward's variance
that input i explains beyond the others (at most 0.5 nats, for an input that explains all of it), and
S^i is a parent of the reward when it is at least the reward threshold (0.01 nats: 2% of the reward's
variance). Assumption 7 (factors affect the reward independently) is what makes one drop-one test per
factor enough.

Why not one variance per mask, its maximum-likelihood value (the mask's MSE; CMI ``0.5 log(MSE_{-i} /
MSE)``), which this module used before (issue 19): a task reward is often a deterministic function of
its parents, so the full model's MSE falls to the size of its residual fitting errors and the log
ratio measures how the residual errors of two sub-networks compare, not what input i tells. On
chemical-distractors (match-first, 20,000 random-policy transitions) the full mask's held-out MSE
fell to 0.002 of a reward variance of 0.16 after 1,000 updates, and inputs the reward ignores scored
-0.3 to +0.17 nats, 3-20 of the 20 above the 0.01 threshold at every estimate, while with the shared
variance they stayed below 0.006 from 1,000 updates on (true parents 0.26-0.50): docs/deviations.md.
A variance per sample (a heteroscedastic head) was tried before either: its held-out likelihood
ratios swung by up to 0.1 nats for inputs the reward ignores.

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
        """Reward CMI of every input ``[I]`` (factors, then the action), nats:
        ``(MSE_{-i} - MSE) / (2 Var(r))``, the expected log-likelihood ratio of two Gaussians sharing the
        reward's variance. Inputs constant over the samples get 0 (a constant carries no information),
        and every input gets 0 when the reward itself is constant (nothing to explain)."""
        return self.cmi_with_stderr(state, action, reward, chunk, zero_constant_inputs)[0]

    @torch.no_grad()
    def cmi_with_stderr(self, state: torch.Tensor, action: torch.Tensor, reward: torch.Tensor, chunk: int = 1024,
                        zero_constant_inputs: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`cmi` and its standard error ``[I]`` over the samples: the CMI is the mean of the
        per-sample terms ``(ei - e0) / (2 Var(r))`` (squared errors with input ``i`` dropped, ``ei``,
        and under the full mask, ``e0``; the variance taken as known), so its standard error is their
        spread over ``sqrt(n)``. Zero wherever :meth:`cmi` is set to 0."""
        n_inputs = self.layout.num_factors + 1
        sums = torch.zeros(n_inputs, dtype=torch.float64)
        squares = torch.zeros_like(sums)
        for start in range(0, state.shape[0], chunk):
            errors = self.squared_errors(*(t[start : start + chunk] for t in (state, action, reward))).double()
            gains = errors[1:] - errors[:1]
            sums += gains.sum(dim=1)
            squares += gains.square().sum(dim=1)
        n = state.shape[0]
        spread = float(reward.to(torch.float64).var()) if reward.numel() > 1 else 0.0
        if spread <= 0.0:
            return torch.zeros(n_inputs), torch.zeros(n_inputs)
        cmi = (sums / n / (2 * spread)).to(torch.float32)
        variance = (squares / n - (sums / n).square()).clamp_min(0.0) * n / max(n - 1, 1)
        stderr = ((variance / n).sqrt() / (2 * spread)).to(torch.float32)
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
