"""Planning with a learned dynamics model and reward predictor (dissertation ch. 3.2.4).

:class:`CEMPlanner` is the cross-entropy method over action sequences of length L: a Normal belief
starting from the unit normal for continuous actions, a Categorical belief starting uniform for
discrete ones; each iteration samples candidates, scores them by the cumulative predicted reward of
a model rollout, and refits the belief to the top candidates. It returns mu_t, or argmax omega_t.

The model is reached only through ``step_fn(states, actions) -> next_states`` and
``reward_fn(states, actions) -> rewards`` on flat batches (a categorical action is its index in
column 0, the convention of flat transitions), so any model plugs in. :func:`cdl_rollout_step`
builds ``step_fn`` from a :class:`CDLModel` in causal mode: each factor predicted from its parents
only. Given the factors an abstraction keeps, it rolls out only those and leaves the rest as they
are, which is planning in the abstract space (the kept set is closed under parents, so the kept
predictions never read a held factor). Trailing columns beyond the model's state (e.g. provided
goal factors) are carried through unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
import torch.nn.functional as F

from causal.cdl import CDLModel
from causal.factored import FactorCodec
from causal.rl.base import ActionSpec, abstraction_input_mask

StepFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""(states [B, D], actions [B, A]) -> next states [B, D]."""
RewardFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""(states [B, D], actions [B, A]) -> rewards [B]."""


@dataclass(frozen=True)
class CEMConfig:
    """CEM search; defaults are the CDL reference (horizon 3, 5 iterations, 64 candidates, top 32)."""

    horizon: int = 3
    iterations: int = 5
    population: int = 64
    elites: int = 32
    discount: float = 1.0
    """Weight gamma^t of the predicted reward t steps ahead."""

    def __post_init__(self) -> None:
        if not 0 < self.elites <= self.population:
            raise ValueError(f"need 0 < elites <= population, got {self.elites} and {self.population}")


class CEMPlanner:
    """The cross-entropy method over action sequences, batched over start states."""

    def __init__(self, step_fn: StepFn, reward_fn: RewardFn, action: ActionSpec, cfg: CEMConfig = CEMConfig(),
                 seed: int = 0) -> None:
        self.step_fn, self.reward_fn, self.action, self.cfg = step_fn, reward_fn, action, cfg
        self.generator = torch.Generator().manual_seed(seed)

    @torch.no_grad()
    def plan(self, states: torch.Tensor) -> torch.Tensor:
        """First actions of the best sequences: long ``[B]`` (categorical) or ``[B, A]``; ``[D]`` -> one."""
        single = states.dim() == 1
        batch = states[None] if single else states
        actions = self._plan_categorical(batch) if self.action.kind == "categorical" else self._plan_continuous(batch)
        return actions[0] if single else actions

    def sequence_returns(self, states: torch.Tensor, candidates: torch.Tensor) -> torch.Tensor:
        """Cumulative predicted reward ``[B, P]`` of candidate sequences ``[B, P, L, A]`` from ``states`` ``[B, D]``."""
        b, p, horizon, _ = candidates.shape
        s = states.repeat_interleave(p, dim=0)
        total = torch.zeros(b * p)
        for t in range(horizon):
            a = candidates[:, :, t].reshape(b * p, -1)
            total += self.cfg.discount ** t * self.reward_fn(s, a).reshape(b * p)
            if t + 1 < horizon:
                s = self.step_fn(s, a)
        return total.view(b, p)

    def _elites(self, states: torch.Tensor, candidates: torch.Tensor) -> torch.Tensor:
        top = self.sequence_returns(states, candidates).topk(self.cfg.elites, dim=1).indices
        index = top[:, :, None, None].expand(-1, -1, *candidates.shape[2:])
        return candidates.gather(1, index)

    def _plan_continuous(self, states: torch.Tensor) -> torch.Tensor:
        shape = (states.shape[0], self.cfg.horizon, self.action.size)
        mean, std = torch.zeros(shape), torch.ones(shape)
        for _ in range(self.cfg.iterations):
            noise = torch.randn((shape[0], self.cfg.population, *shape[1:]), generator=self.generator)
            elites = self._elites(states, self._bounded(mean[:, None] + std[:, None] * noise))
            mean, std = elites.mean(dim=1), elites.std(dim=1, unbiased=False)
        return self._bounded(mean[:, 0])

    def _plan_categorical(self, states: torch.Tensor) -> torch.Tensor:
        b, horizon, n = states.shape[0], self.cfg.horizon, self.action.size
        probs = torch.full((b, horizon, n), 1.0 / n)
        for _ in range(self.cfg.iterations):
            draws = torch.multinomial(probs.reshape(b * horizon, n), self.cfg.population, replacement=True,
                                      generator=self.generator)
            candidates = draws.view(b, horizon, -1).transpose(1, 2)[..., None].float()
            elites = self._elites(states, candidates)[..., 0].long()
            probs = F.one_hot(elites, n).float().mean(dim=1)
        return probs[:, 0].argmax(dim=-1)

    def _bounded(self, actions: torch.Tensor) -> torch.Tensor:
        if not self.action.low:
            return actions
        return actions.clamp(torch.tensor(self.action.low), torch.tensor(self.action.high))


def cdl_outputs(model: CDLModel, state: torch.Tensor, action: torch.Tensor, parents: torch.Tensor) -> torch.Tensor:
    """Raw head outputs ``[d_S, B, head_width]`` with each factor's inputs masked to ``parents``
    (``[d_S, d_S + 1]`` bool, graph column order, action last); only the parents' feature networks run."""
    return model.masked_outputs(state, action, parents)


def next_state_from_outputs(codec: FactorCodec, out: torch.Tensor, state: torch.Tensor, sample: bool = False,
                            generator: torch.Generator | None = None,
                            log_std_range: tuple[float, float] = (-6.0, 2.0), target: str = "delta") -> torch.Tensor:
    """The predicted next flat state from head outputs ``[d_S, B, O]``: the arg-max (or a sample)
    of each categorical factor, the mean (or a sample) of each continuous one, a change added to the
    state's value (``target`` "delta") or the next value itself ("next", ``CDLConfig.target``); extra
    columns copied."""
    nxt = state.clone()
    if codec.cat_factors:
        nxt[:, codec.cat_cols] = _categorical_prediction(codec, out, sample, generator).T.to(state.dtype)
    if codec.cont_factors:
        m, valid = codec.max_cont, codec.cont_valid
        raw = out[codec.cont_index]
        change = raw[..., :m]
        if sample:
            log_std = raw[..., m : 2 * m].clamp(*log_std_range)
            change = change + log_std.exp() * torch.randn(change.shape, generator=generator)
        predicted = change.transpose(0, 1) * codec.cont_scale[None, :, None]
        # a change is added to the state's value; a next value is in the codec's normalised units
        base = state[:, codec.cont_cols] if target == "delta" else codec.cont_loc[None, :, None]
        predicted = predicted + base
        nxt[:, codec.cont_cols[valid]] = predicted[:, valid].to(state.dtype)
    return nxt


def _categorical_prediction(codec: FactorCodec, out: torch.Tensor, sample: bool,
                            generator: torch.Generator | None) -> torch.Tensor:
    logits = out[codec.cat_index, :, : codec.max_cat]
    valid = torch.arange(codec.max_cat) < codec.cat_sizes[:, None]
    logits = logits.masked_fill(~valid[:, None, :], float("-inf"))
    if not sample:
        return logits.argmax(dim=-1)
    flat = torch.softmax(logits, dim=-1).reshape(-1, codec.max_cat)
    return torch.multinomial(flat, 1, generator=generator).view(logits.shape[:2])


def predicted_next_state(model: CDLModel, state: torch.Tensor, action: torch.Tensor, parents: torch.Tensor,
                         sample: bool = False, generator: torch.Generator | None = None) -> torch.Tensor:
    """CDL's causal-mode prediction of the next flat state (self-edges always kept, Assumption 4)."""
    parents = parents.to(torch.bool) | _self_edges(model.layout.num_factors)
    out = cdl_outputs(model, state, action, parents)
    log_std_range = (model.cfg.log_std_min, model.cfg.log_std_max)
    return next_state_from_outputs(model.codec, out, state, sample, generator, log_std_range, model.cfg.target)


def cdl_rollout_step(model: CDLModel, parents: torch.Tensor, factors: Sequence[int] | None = None,
                     sample: bool = False, generator: torch.Generator | None = None) -> StepFn:
    """``step_fn`` for :class:`CEMPlanner` from a CDL model in causal mode.

    ``factors`` (e.g. ``Abstraction.kept``) are rolled out, every other column is held; None rolls
    out every factor.
    """
    columns = None if factors is None else torch.from_numpy(abstraction_input_mask(model.layout, factors))

    @torch.no_grad()
    def step(states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        predicted = predicted_next_state(model, states, actions, parents, sample, generator)
        if columns is None:
            return predicted
        held = torch.zeros(states.shape[1] - columns.shape[0], dtype=torch.bool)
        return torch.where(torch.cat([columns, held]), predicted, states)

    return step


def _self_edges(num_factors: int) -> torch.Tensor:
    return torch.cat([torch.eye(num_factors, dtype=torch.bool), torch.zeros(num_factors, 1, dtype=torch.bool)], 1)
