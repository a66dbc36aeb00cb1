"""Dyn-O's static/dynamic split of each slot (dissertation section 7.2.2, eqs. 7.3-7.5).

    c^k = M_c(xi^k) (static),  v^k = M_v(xi^k) (dynamic),  xi^^k = M_xi(sg(c^k), v^k)
    L_stat = sum_{k, t != t'} ||c_t^k - c_t'^k||^2 + InfoNCE(c_t^k; positive c_t'^k, negatives: other slots)  (7.3)
    L_dyn  = sum_k ||xi^^k - xi^k||^2 + Disc(c^k, v^k)                                                      (7.4)
    L_disc = sum_k (-Disc(c^k, v^k) + Disc(c^k, v^k')) + LeCam(Disc)                                       (7.5)

``Disc`` is a Wasserstein critic told pairs of one slot from pairs of two; ``M_v`` is trained against
it (a gradient-reversal-free alternation), so the dynamic features carry little of what the static
ones hold. LeCam regularisation (Tseng et al. 2021) pulls the critic's outputs on one kind of pair
towards a running mean of its outputs on the other kind.

Where the chapter writes InfoNCE with cosines in place of the usual exponentials (which a negative
cosine would make undefined), this uses ``exp(cos / temperature)``: a deviation, docs/deviations.md.
:func:`linear_probe` is Table 7.5's probe: a linear classifier over binned targets.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from proto.settings import doc


@dataclass(frozen=True)
class SplitConfig:
    """Sizes and weights of eqs. 7.3-7.5."""

    static_dim: int = doc(16, "d_c: size of a slot's static features")
    dynamic_dim: int = doc(16, "d_v: size of a slot's dynamic features")
    hidden: int = doc(64, "hidden width of M_c, M_v, M_xi and Disc")
    temperature: float = doc(0.1, "InfoNCE temperature on cosine similarities")
    lecam_weight: float = doc(0.1, "weight of the LeCam regulariser in eq. 7.5")
    lecam_decay: float = doc(0.99, "decay of the critic's running output means LeCam pulls towards")
    disentangle_weight: float = doc(0.1, "weight of Disc(c, v) in eq. 7.4")
    lr: float = doc(1e-3, "Adam learning rate of every part")
    critic_steps: int = doc(1, "critic updates (eq. 7.5) per update of the features (eqs. 7.3-7.4); WGAN's "
                               "usual is 5, the chapter does not say")
    critic_spectral_norm: bool = doc(False, "spectral normalisation of the critic's layers, which makes it "
                                            "1-Lipschitz as a Wasserstein critic must be (the chapter names "
                                            "only LeCam; without a bound the features can fool the critic by "
                                            "moving v where it scores low instead of removing c from it)")
    critic_standardise: bool = doc(False, "the critic reads (c, v) standardised per channel over the batch "
                                          "(statistics with gradient): a channel the features shrink is "
                                          "still seen at full scale, as a linear probe on standardised "
                                          "features sees it (not in the chapter)")

    def __post_init__(self) -> None:
        if min(self.static_dim, self.dynamic_dim, self.hidden, self.critic_steps) < 1:
            raise ValueError("static_dim, dynamic_dim, hidden and critic_steps must be >= 1")
        if not (self.temperature > 0 and self.lr > 0 and 0 <= self.lecam_decay < 1):
            raise ValueError("temperature and lr must be > 0 and lecam_decay in [0, 1)")
        if self.lecam_weight < 0 or self.disentangle_weight < 0:
            raise ValueError("lecam_weight and disentangle_weight must be >= 0")


def _mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, outputs))


class SplitLosses(NamedTuple):
    static: torch.Tensor
    dynamic: torch.Tensor
    critic: torch.Tensor


class StaticDynamicSplit(nn.Module):
    """M_c, M_v, M_xi and Disc over slots ``[..., d_xi]``."""

    def __init__(self, slot_dim: int, config: SplitConfig) -> None:
        super().__init__()
        self.config = config
        self.static = _mlp(slot_dim, config.hidden, config.static_dim)
        self.dynamic = _mlp(slot_dim, config.hidden, config.dynamic_dim)
        self.reconstruct = _mlp(config.static_dim + config.dynamic_dim, config.hidden, slot_dim)
        self.critic = _mlp(config.static_dim + config.dynamic_dim, config.hidden, 1)
        if config.critic_spectral_norm:
            for index, layer in enumerate(self.critic):
                if isinstance(layer, nn.Linear):
                    self.critic[index] = nn.utils.parametrizations.spectral_norm(layer)
        self.register_buffer("mean_same", torch.zeros(()))
        self.register_buffer("mean_other", torch.zeros(()))

    def disc(self, static: torch.Tensor, dynamic: torch.Tensor) -> torch.Tensor:
        pair = torch.cat([static, dynamic], dim=-1)
        if self.config.critic_standardise:
            flat = pair.reshape(-1, pair.shape[-1])
            pair = (pair - flat.mean(0)) / (flat.std(0) + 1e-6)
        return self.critic(pair)[..., 0]

    def losses(self, slots: torch.Tensor) -> SplitLosses:
        """Eqs. 7.3-7.5 (means) on slot sequences ``[B, T, K, d_xi]`` whose slot ``k`` is one object over time."""
        c, v = self.static(slots), self.dynamic(slots)
        static = time_invariance(c) + info_nce(c, self.config.temperature)
        shuffled = _other_slots(v)
        reconstruction = F.mse_loss(self.reconstruct(torch.cat([c.detach(), v], dim=-1)), slots)
        dynamic = reconstruction + self.config.disentangle_weight * self.disc(c.detach(), v).mean()
        same, other = self.disc(c.detach(), v.detach()), self.disc(c.detach(), shuffled.detach())
        critic = -same.mean() + other.mean() + self.config.lecam_weight * self._lecam(same, other)
        return SplitLosses(static, dynamic, critic)

    def _lecam(self, same: torch.Tensor, other: torch.Tensor) -> torch.Tensor:
        """||D(same) - mean D(other)||^2 + ||D(other) - mean D(same)||^2, the means running (EMA)."""
        penalty = (same - self.mean_other).square().mean() + (other - self.mean_same).square().mean()
        if self.training:
            decay = self.config.lecam_decay
            self.mean_same.mul_(decay).add_((1 - decay) * same.detach().mean())
            self.mean_other.mul_(decay).add_((1 - decay) * other.detach().mean())
        return penalty


def time_invariance(static: torch.Tensor) -> torch.Tensor:
    """Mean over slots and ordered pairs t != t' of ||c_t^k - c_t'^k||^2, for ``[B, T, K, d]``."""
    t = static.shape[1]
    differences = (static[:, :, None] - static[:, None]).square().sum(-1)
    return differences.sum(dim=(1, 2)).mean() / max(t * (t - 1), 1)


def info_nce(static: torch.Tensor, temperature: float) -> torch.Tensor:
    """Cosine InfoNCE: for each c_t^k the positive is the same slot at the next time step (cyclically),
    the negatives every other slot of the batch at any time step (the same slot's other steps are
    left out: they are no negatives)."""
    b, t, k, d = static.shape
    anchors = F.normalize(static, dim=-1).reshape(b * t * k, d)
    positives = F.normalize(static.roll(-1, dims=1), dim=-1).reshape(b * t * k, d)
    logits = anchors @ positives.T / temperature
    slot = (torch.arange(b)[:, None, None] * k + torch.arange(k)).expand(b, t, k).reshape(-1)
    same_slot = (slot[:, None] == slot[None, :]) & ~torch.eye(b * t * k, dtype=torch.bool)
    return F.cross_entropy(logits.masked_fill(same_slot, float("-inf")), torch.arange(b * t * k))


def _other_slots(dynamic: torch.Tensor) -> torch.Tensor:
    """Each slot's dynamic features replaced by another slot's of the same frame (a cyclic shift over k)."""
    return dynamic.roll(1, dims=2)


def linear_probe(train_x: torch.Tensor, train_y: torch.Tensor, test_x: torch.Tensor, test_y: torch.Tensor,
                 classes: int, steps: int = 300, seed: int = 0) -> float:
    """Accuracy on the test rows of a linear classifier (softmax regression, standardised inputs,
    Adam on the training rows): Table 7.5's probe."""
    torch.manual_seed(seed)
    mean, std = train_x.mean(0), train_x.std(0) + 1e-6
    x, xt = (train_x - mean) / std, (test_x - mean) / std
    probe = nn.Linear(x.shape[1], classes)
    optimizer = torch.optim.Adam(probe.parameters(), lr=0.05)
    for _ in range(steps):
        loss = F.cross_entropy(probe(x), train_y)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        return float((probe(xt).argmax(1) == test_y).float().mean())


def bins(values: torch.Tensor, count: int = 10) -> torch.Tensor:
    """Equal-width bins (0 .. count - 1) of ``values`` over their range."""
    low, high = float(values.min()), float(values.max())
    return ((values - low) / max(high - low, 1e-12) * count).long().clamp(0, count - 1)
