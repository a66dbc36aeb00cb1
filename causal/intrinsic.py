"""Intrinsic rewards from a learned causal dynamics model (no bus).

A reward maps transitions ``(s, a, s')`` to one float per transition, given the CDL model and the
causal parents ``PA(j)`` of every next-state factor (a ``d_S x (d_S + 1)`` graph, self-edges forced).
Rewards live in a small registry (:data:`REWARDS`) so new ones (ELDEN's, an ensemble's) can join.

* ``preddiff`` (CDL, eq. 3.4): ``r = tanh(eta * sum_j log p(s'_j | s, a) / p(s'_j | PA(j)))``, the
  dense predictor against the causal one: large where the causal model misses something.
* ``curiosity`` (dynamics curiosity, Burda et al. 2019): prediction error, ``eta * sum_j -log p(s'_j)``
  of the run's dynamics model: CDL's causal predictor (``p(s'_j | PA(j))``), or any model that
  gives its own :meth:`PredictionErrorModel.prediction_nll` (ELDEN: the ensemble's mean NLL).
* ``disagreement``: ``eta * sum_d Var_k f_k(s, a)_d`` across the K members of a
  :class:`BootstrapEnsemble` of forward models, each trained on its own bootstrap resample
  (Poisson(1) weight per member and transition, fixed when the transition arrives).
* ``elden`` (ELDEN, Algorithm 6): ``eta * mean over edges of Var_k G_k(s, a)``, the variance across
  the ensemble members of each edge of their local dependency graphs (eq. 5.1), zero for outputs
  on whose next value the members agree; zero until the weights have seen the model's warm-up of
  env steps (:meth:`IntrinsicReward.warmup_env_steps`).

The first two share one feature computation: the dense and the causal aggregate are two masks on it.
A reward's ``source`` says which model it reads: ``dynamics`` (the run's method's published weights;
the method lists the rewards its model serves in ``Method.intrinsic``) or ``ensemble`` (a model the
intrinsic-reward service trains itself, whatever the method).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar, Protocol, runtime_checkable

import numpy as np
import torch

from torch import nn

from causal.cdl import CDLModel
from causal.abstraction import with_self_edges
from causal.elden import ELDENModel
from causal.elden_graphs import graph_variance
from causal.factored import FactorCodec, FactorLayout


class IntrinsicReward(Protocol):
    """Rewards ``[B]`` for transitions, from a dynamics model and its causal parents."""

    name: ClassVar[str]
    source: ClassVar[str]

    def __call__(self, model: nn.Module, parents: np.ndarray, state: torch.Tensor, action: torch.Tensor,
                 next_state: torch.Tensor) -> torch.Tensor: ...

    def warmup_env_steps(self, model: nn.Module) -> int:
        """Env steps the weights must have seen before this reward is non-zero (0: none)."""


class _NoWarmup:
    def warmup_env_steps(self, model: nn.Module) -> int:
        return 0


@runtime_checkable
class PredictionErrorModel(Protocol):
    """A dynamics model that scores its own prediction error (what ``curiosity`` reads)."""

    def prediction_nll(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        """``-log p(s' | s, a)`` summed over factors, ``[B]`` nats."""


def causal_parents(adjacency: np.ndarray) -> torch.Tensor:
    """A graph ``[d_S, d_S + 1]`` as a bool parent mask with self-edges (Assumption 4)."""
    return torch.from_numpy(with_self_edges(adjacency))


@torch.no_grad()
def dense_and_causal_nll(model: CDLModel, parents: np.ndarray, state: torch.Tensor, action: torch.Tensor,
                         next_state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """NLL ``[J, B]`` of every next-state factor under the dense predictor (every input) and the
    causal predictor (inputs ``PA(j)`` only), from one feature computation."""
    feats = model.features(state, action)
    keep = model.to_group_order(causal_parents(parents).to(feats.device))
    dense = feats.amax(dim=1, keepdim=True)
    causal = feats.masked_fill(~keep[:, :, None, None], float("-inf")).amax(dim=1, keepdim=True)
    nll = model.nll(model.predict(torch.cat([dense, causal], dim=1)), state, next_state)
    return nll[:, 0], nll[:, 1]


@dataclass(frozen=True)
class PredDiff(_NoWarmup):
    """CDL's prediction difference (eq. 3.4), squashed by tanh into (-1, 1)."""

    name: ClassVar[str] = "preddiff"
    source: ClassVar[str] = "dynamics"
    eta: float = 1.0

    def __call__(self, model: CDLModel, parents: np.ndarray, state: torch.Tensor, action: torch.Tensor,
                 next_state: torch.Tensor) -> torch.Tensor:
        dense, causal = dense_and_causal_nll(model, parents, state, action, next_state)
        return torch.tanh(self.eta * (causal - dense).sum(dim=0))


@dataclass(frozen=True)
class PredictionError(_NoWarmup):
    """Dynamics curiosity: the model's NLL of the observed next state, summed over factors (CDL: the
    causal predictor's; a :class:`PredictionErrorModel`: its own)."""

    name: ClassVar[str] = "curiosity"
    source: ClassVar[str] = "dynamics"
    eta: float = 1.0

    def __call__(self, model: CDLModel | PredictionErrorModel, parents: np.ndarray, state: torch.Tensor,
                 action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        if isinstance(model, CDLModel):
            _, causal = dense_and_causal_nll(model, parents, state, action, next_state)
            return self.eta * causal.sum(dim=0)
        if not isinstance(model, PredictionErrorModel):
            raise TypeError(f"{type(model).__name__} gives no prediction error")
        with torch.no_grad():
            return self.eta * model.prediction_nll(state, action, next_state)


class BootstrapEnsemble(nn.Module):
    """K forward models ``(s, a) -> encoded s'`` (one-hot categories, normalised values) as stacked
    tensors, with a replay whose rows carry one Poisson(1) bootstrap weight per member."""

    def __init__(self, layout: FactorLayout, members: int = 5, hidden: int = 64, lr: float = 1e-3,
                 capacity: int = 50_000, seed: int = 0) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.codec = FactorCodec(layout)
        self.members = members
        inputs = layout.num_factors * layout.input_width + layout.action_width
        outputs = layout.num_factors * layout.input_width
        widths = [(inputs, hidden), (hidden, hidden), (hidden, outputs)]
        self.weights = nn.ParameterList([nn.Parameter(torch.randn(members, i, o) / i**0.5) for i, o in widths])
        self.biases = nn.ParameterList([nn.Parameter(torch.zeros(members, 1, o)) for _, o in widths])
        self.optimizer = torch.optim.Adam(self.parameters(), lr=lr)
        self.rng = np.random.default_rng(seed)
        action_dim = 1 if layout.action_kind == "categorical" else layout.action_size
        widths_of = {"state": layout.state_dim, "action": action_dim, "next_state": layout.state_dim, "boot": members}
        self.rows = {name: np.zeros((capacity, width), np.float32) for name, width in widths_of.items()}
        self.size = self.cursor = self.updates = 0

    def predict(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Every member's prediction ``[K, B, outputs]``."""
        x = torch.cat([self.codec.encode_state(state).flatten(1), self.codec.encode_action(action)], dim=1)
        x = x.expand(self.members, -1, -1)
        for n, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(b, x, w)
            x = torch.relu(x) if n < len(self.weights) - 1 else x
        return x

    @torch.no_grad()
    def disagreement(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``sum_d Var_k`` of the members' predictions, ``[B]``."""
        return self.predict(state, action).var(dim=0, unbiased=False).sum(-1)

    def add(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray) -> None:
        """Store transitions, each with a Poisson(1) weight per member (its bootstrap multiplicity)."""
        boot = self.rng.poisson(1.0, (len(state), self.members)).astype(np.float32)
        capacity = len(self.rows["boot"])
        index = (self.cursor + np.arange(len(state))) % capacity
        for name, values in (("state", state), ("action", action), ("next_state", next_state), ("boot", boot)):
            self.rows[name][index] = values
        self.cursor = int((self.cursor + len(state)) % capacity)
        self.size = min(capacity, self.size + len(state))

    def train_step(self, batch_size: int) -> float:
        """One Adam step on a uniform sample; member k's squared error is weighted by its bootstrap weights."""
        index = self.rng.integers(0, self.size, batch_size)
        s, a, n, boot = (torch.from_numpy(self.rows[k][index]) for k in ("state", "action", "next_state", "boot"))
        error = (self.predict(s, a) - self.codec.encode_state(n).flatten(1)).square().sum(-1)
        loss = (error * boot.T).sum() / boot.sum().clamp_min(1.0)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        return loss.item()


@dataclass(frozen=True)
class Disagreement(_NoWarmup):
    """Ensemble disagreement: the variance of K bootstrap forward models' predictions, summed."""

    name: ClassVar[str] = "disagreement"
    source: ClassVar[str] = "ensemble"
    eta: float = 1.0

    def __call__(self, model: BootstrapEnsemble, parents: np.ndarray, state: torch.Tensor, action: torch.Tensor,
                 next_state: torch.Tensor) -> torch.Tensor:
        return self.eta * model.disagreement(state, action)


@dataclass(frozen=True)
class LocalGraphVariance:
    """ELDEN's reward (Algorithm 6, lines 4-5): the variance of the members' local graphs, times beta."""

    name: ClassVar[str] = "elden"
    source: ClassVar[str] = "dynamics"
    eta: float = 1.0
    """beta of Algorithm 6 (reference: 1)."""

    def __call__(self, model: ELDENModel, parents: np.ndarray, state: torch.Tensor, action: torch.Tensor,
                 next_state: torch.Tensor) -> torch.Tensor:
        return self.eta * graph_variance(model, state, action, next_state)

    def warmup_env_steps(self, model: ELDENModel) -> int:
        return model.cfg.reward_warmup_env_steps


REWARDS: dict[str, Callable[..., IntrinsicReward]] = {
    PredDiff.name: PredDiff, PredictionError.name: PredictionError, Disagreement.name: Disagreement,
    LocalGraphVariance.name: LocalGraphVariance}
"""Intrinsic rewards by name; each factory takes ``eta``."""


def reward_names() -> tuple[str, ...]:
    return tuple(REWARDS)


def make_reward(name: str, eta: float = 1.0) -> IntrinsicReward:
    """The registered reward ``name``; unknown names raise ``KeyError`` listing the known ones."""
    try:
        return REWARDS[name](eta=eta)
    except KeyError:
        raise KeyError(f"unknown intrinsic reward {name!r}; known: {sorted(REWARDS)}") from None


def score(reward: IntrinsicReward, model: nn.Module, parents: np.ndarray, state: np.ndarray,
          action: np.ndarray, next_state: np.ndarray, chunk: int = 1024,
          device: torch.device = torch.device("cpu")) -> np.ndarray:
    """``reward`` on numpy transitions, in chunks of ``chunk`` rows moved to ``device`` (the model's);
    float32 ``[B]``."""
    out = []
    for start in range(0, len(state), chunk):
        s, a, n = (torch.from_numpy(np.ascontiguousarray(x[start : start + chunk], np.float32))
                   .to(device) for x in (state, action, next_state))
        out.append(reward(model, parents, s, a, n).cpu().numpy())
    return np.concatenate(out).astype(np.float32) if out else np.zeros(0, np.float32)
