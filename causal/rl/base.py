"""The agent interface and the typed batches agents learn from.

An :class:`Agent` is what a policy-learner drives: it acts, it learns from one batch at a time, it
counts its policy ``version`` (one per update, so trajectories can say which policy produced them
and learners can bound policy lag), and its state round-trips through ``state_dict``.

The *input mask* is how a learned state abstraction reaches a policy: a boolean vector over
observation dimensions whose False entries are zeroed before any network sees them.
:func:`abstraction_input_mask` builds it from the factors an abstraction keeps.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, Protocol, Sequence, runtime_checkable

import gymnasium as gym
import numpy as np
import torch

from causal.factored import FactorLayout


@dataclass(frozen=True)
class ActionSpec:
    """An action space in the factored vocabulary: ``categorical`` (``size`` choices) or
    ``continuous`` (``size`` dimensions bounded by ``low`` and ``high``)."""

    kind: str
    size: int
    low: tuple[float, ...] = ()
    high: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in ("categorical", "continuous"):
            raise ValueError(f"action kind must be categorical or continuous, got {self.kind!r}")
        if self.kind == "continuous" and (len(self.low) != self.size or len(self.high) != self.size):
            raise ValueError(f"continuous actions need {self.size} low and high bounds")

    @classmethod
    def from_space(cls, space: gym.Space) -> "ActionSpec":
        """From a gymnasium ``Discrete`` or one-dimensional ``Box`` space."""
        if isinstance(space, gym.spaces.Discrete):
            return cls("categorical", int(space.n))
        if isinstance(space, gym.spaces.Box) and len(space.shape) == 1:
            return cls("continuous", int(space.shape[0]), tuple(map(float, space.low)), tuple(map(float, space.high)))
        raise TypeError(f"unsupported action space {space}")

    @property
    def dim(self) -> int:
        """Width of one action in a batch: 1 (the index) or the number of dimensions."""
        return 1 if self.kind == "categorical" else self.size


@dataclass(frozen=True)
class RolloutBatch:
    """On-policy steps of ``N`` parallel environments over ``T`` steps, time-major.

    ``actions`` are the *sampled* actions (category indices ``[T, N]`` long, or the raw Gaussian
    sample ``[T, N, A]`` before clipping or squashing) and ``log_probs`` their behaviour
    log-probabilities. ``dones[t]`` is True when an episode ended after step t; a truncated
    episode's bootstrap value is already folded into its last reward. ``last_obs`` follows the last
    step, for the bootstrap of unfinished episodes.
    """

    obs: torch.Tensor
    actions: torch.Tensor
    log_probs: torch.Tensor
    values: torch.Tensor
    rewards: torch.Tensor
    dones: torch.Tensor
    last_obs: torch.Tensor
    policy_version: int = 0

    def __post_init__(self) -> None:
        steps = tuple(self.rewards.shape)
        for name in ("obs", "actions", "log_probs", "values", "dones"):
            if tuple(getattr(self, name).shape[:2]) != steps:
                raise ValueError(f"{name} leads with {tuple(getattr(self, name).shape[:2])}, rewards with {steps}")
        if tuple(self.last_obs.shape) != (steps[1], self.obs.shape[-1]):
            raise ValueError(f"last_obs shape {tuple(self.last_obs.shape)} != {(steps[1], self.obs.shape[-1])}")


@dataclass(frozen=True)
class ReplayBatch:
    """Uniformly sampled transitions for an off-policy learner; ``terminated`` excludes truncation."""

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor

    def __post_init__(self) -> None:
        n = self.rewards.shape[0]
        for name in ("obs", "actions", "next_obs", "terminated"):
            if getattr(self, name).shape[0] != n:
                raise ValueError(f"{name} has {getattr(self, name).shape[0]} rows, rewards {n}")


@runtime_checkable
class Agent(Protocol):
    """A policy that acts and learns; ``version`` counts its updates."""

    version: int

    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Actions for observations ``[B, obs_dim]`` (or one ``[obs_dim]``), in the env's format."""
        ...

    def update(self, batch: Any) -> dict[str, float]:
        """One learning step on ``batch``; returns scalar statistics."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Networks, optimisers and version, loadable with ``torch.load(..., weights_only=True)``."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        ...


def on_device(batch: Any, device: torch.device) -> Any:
    """A :class:`RolloutBatch` or :class:`ReplayBatch` with its tensors on ``device`` (itself if they are)."""
    tensors = {f.name: getattr(batch, f.name) for f in fields(batch) if isinstance(getattr(batch, f.name), torch.Tensor)}
    if all(t.device == device for t in tensors.values()):
        return batch
    return replace(batch, **{name: t.to(device) for name, t in tensors.items()})


def abstraction_input_mask(layout: FactorLayout, kept: Sequence[int], extra_dims: int = 0) -> np.ndarray:
    """Boolean mask over a flat observation keeping the slots of factors ``kept`` (e.g.
    ``Abstraction.kept``) and the ``extra_dims`` trailing dimensions (e.g. provided goal factors)."""
    mask = np.zeros(layout.state_dim + extra_dims, dtype=bool)
    offsets = layout.offsets()
    for j in kept:
        mask[offsets[j] : offsets[j] + layout.slots(j)] = True
    mask[layout.state_dim :] = True
    return mask


def mask_tensor(mask: np.ndarray | Sequence[bool] | None, obs_dim: int) -> torch.Tensor:
    """A float ``[obs_dim]`` multiplier from a boolean mask; None keeps every dimension."""
    if mask is None:
        return torch.ones(obs_dim)
    out = torch.as_tensor(np.asarray(mask, dtype=bool), dtype=torch.float32)
    if out.shape != (obs_dim,):
        raise ValueError(f"input mask shape {tuple(out.shape)} != ({obs_dim},)")
    return out


def as_batch(obs: np.ndarray | torch.Tensor) -> tuple[torch.Tensor, bool]:
    """Observations as a float32 ``[B, D]`` tensor, and whether a single one was given."""
    tensor = torch.as_tensor(np.asarray(obs, dtype=np.float32))
    single = tensor.dim() == 1
    return (tensor[None] if single else tensor), single
