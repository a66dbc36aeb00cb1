"""SkiLD (dissertation ch. 6): skills defined by the local dependencies they induce. Pure core.

A skill is ``z = (G, b)``: a target local graph ``G`` and a diversity index ``b`` in ``{0 .. K-1}``
(6.2.1). As in the chapter's factorised low level, a target is one factor's row of the graph: the
factor ``j`` that should be influenced and the set of its parents (the other factors and the action)
that must be, and only be, its parents at ``t + 1``. Factors are the chapter's: objects (the agent,
the printer, ...), so an env's per-attribute local graph ``[d_S, d_S + 1]`` is pooled to objects
(:func:`object_graphs`): object ``J`` depends on ``I`` when some attribute of ``J`` depends on some
attribute of ``I``.

- :class:`GraphHistory`: every induced row per factor with its sightings count; a row becomes a
  target once seen ``eligible_after`` (20) times, at most ``max_targets`` (256) targets (6.2.2).
- :func:`novelty_reward`: the graph-selection reward ``count(G)^(-1/2)`` (eq. 6.1).
- :func:`skill_reward`: ``1[induced row = target row] * (1 + lambda_b log q(b | s', G))`` (eq. 6.2).
- :class:`DiversityDiscriminator`: DIAYN's ``q(b | s, G)``, a small MLP on the state's one-hots and
  the target, batched.
- :func:`hindsight_relabel`: a fraction (7/8) of samples relabelled to a row induced at that step or
  a later one of its episode (HER's "future" strategy, up to ``relabel_horizon - 1`` steps on),
  preferring rarely seen rows; rewards are recomputed with :func:`skill_reward` from the replayed
  step's own graph, so they stay consistent with the labels.

Everything works on batches (numpy for graphs and counts, torch for the discriminator).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from proto.settings import doc


@dataclass(frozen=True)
class SkiLDConfig:
    """SkiLD (ch. 6): skill space, graph history, rewards and relabelling of reward-free skill discovery."""

    diversity_k: int = doc(4, "K: diversity indices b per target graph (uniform over {0 .. K-1})")
    eligible_after: int = doc(20, "sightings after which an induced graph becomes a target")
    max_targets: int = doc(256, "most targets the graph history holds")
    skill_steps: int = doc(20, "L: steps a selected skill runs before the high level picks again")
    diversity_weight: float = doc(0.5, "lambda_b: weight of the diversity reward log q(b | s, G) (eq. 6.2)")
    relabel_fraction: float = doc(0.875, "share of replayed samples relabelled to a graph they induced (hindsight)")
    relabel_horizon: int = doc(1, "hindsight targets come from the graph induced at the replayed step or up to this "
                                  "many steps minus one later in its episode (HER's 'future' strategy, e.g. L = 20); "
                                  "1 (the default): the replayed step's own graph only")
    relabel_random: float = doc(0.0, "share of replayed samples given a target drawn uniformly from the history's "
                                     "targets instead (HER's 'random' strategy), paid by what their own step induced: "
                                     "the unpaid samples every target needs")
    discriminator_hidden: int = doc(64, "hidden width of the diversity discriminator q")
    discriminator_lr: float = doc(1e-3, "Adam learning rate of the diversity discriminator")

    def __post_init__(self) -> None:
        for name in ("diversity_k", "eligible_after", "max_targets", "skill_steps", "relabel_horizon",
                     "discriminator_hidden"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.relabel_fraction <= 1.0:
            raise ValueError(f"relabel_fraction must be in [0, 1], got {self.relabel_fraction}")
        if not 0.0 <= self.relabel_random <= 1.0:
            raise ValueError(f"relabel_random must be in [0, 1], got {self.relabel_random}")
        if not (math.isfinite(self.diversity_weight) and self.diversity_weight >= 0):
            raise ValueError(f"diversity_weight must be a finite number >= 0, got {self.diversity_weight}")
        if not (math.isfinite(self.discriminator_lr) and self.discriminator_lr > 0):
            raise ValueError(f"discriminator_lr must be a positive finite number, got {self.discriminator_lr}")


def object_names(factor_objects: Sequence[str]) -> tuple[str, ...]:
    """The objects of a layout, in order of first appearance (the agent first in household tasks)."""
    return tuple(dict.fromkeys(factor_objects))


def pooling_matrices(factor_objects: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """``rows [N, d_S]`` and ``cols [d_S + 1, N + 1]`` 0/1 matrices: attribute -> object membership,
    the action column mapped to the action column."""
    names = object_names(factor_objects)
    index = np.array([names.index(o) for o in factor_objects])
    d, n = len(factor_objects), len(names)
    rows = np.zeros((n, d), dtype=np.float32)
    rows[index, np.arange(d)] = 1
    cols = np.zeros((d + 1, n + 1), dtype=np.float32)
    cols[np.arange(d), index] = 1
    cols[d, n] = 1
    return rows, cols


def object_graphs(local_graphs: np.ndarray, factor_objects: Sequence[str]) -> np.ndarray:
    """Per-attribute local graphs ``[B, d_S, d_S + 1]`` -> per-object bool ``[B, N, N + 1]``."""
    rows, cols = pooling_matrices(factor_objects)
    pooled = np.einsum("nd,bde,ef->bnf", rows, np.asarray(local_graphs, dtype=np.float32), cols)
    return pooled > 0


def induced_local_graphs(scores: np.ndarray, threshold: float, states: np.ndarray,
                         next_states: np.ndarray) -> np.ndarray:
    """The local graphs a step induced, from an estimator's edge scores ``[B, d_S, d_S + 1]`` (pCMI):
    an edge where the score reaches ``threshold``, self-edges always, and an attribute that did not
    change given only its self-edge (the authors' rule). Bool ``[B, d_S, d_S + 1]``."""
    d = scores.shape[1]
    eye = np.eye(d, d + 1, dtype=bool)
    graphs = (np.asarray(scores) >= threshold) | eye
    unchanged = np.asarray(states) == np.asarray(next_states)
    graphs[unchanged] = eye[np.nonzero(unchanged)[1]]
    return graphs


def row_keys(rows: np.ndarray) -> np.ndarray:
    """Bool rows ``[..., N + 1]`` -> int64 keys (bit ``i`` = parent ``i``); at most 62 parents."""
    width = rows.shape[-1]
    if width > 62:
        raise ValueError(f"graph rows of {width} entries do not fit an int64 key")
    return (np.asarray(rows, dtype=np.int64) << np.arange(width, dtype=np.int64)).sum(axis=-1)


def key_rows(keys: np.ndarray, width: int) -> np.ndarray:
    """Inverse of :func:`row_keys`: int64 keys ``[...]`` -> bool rows ``[..., width]``."""
    return ((np.asarray(keys, dtype=np.int64)[..., None] >> np.arange(width, dtype=np.int64)) & 1).astype(bool)


class GraphHistory:
    """Every row each factor has been seen to induce, with its count, and the targets among them."""

    def __init__(self, num_factors: int, eligible_after: int = 20, max_targets: int = 256) -> None:
        self.num_factors, self.eligible_after, self.max_targets = num_factors, eligible_after, max_targets
        self._counts: list[dict[int, int]] = [{} for _ in range(num_factors)]
        self.targets: list[tuple[int, int]] = []
        """``(factor, row key)`` of each target, in the order they became eligible (a target's slot)."""
        self._target_set: set[tuple[int, int]] = set()

    def update(self, graphs: np.ndarray) -> None:
        """Count the rows of a batch of induced graphs ``[B, N, N + 1]`` (bool)."""
        keys = row_keys(graphs)
        for j in range(self.num_factors):
            counts = self._counts[j]
            for key, n in zip(*np.unique(keys[:, j], return_counts=True)):
                total = counts[int(key)] = counts.get(int(key), 0) + int(n)
                self._maybe_target(j, int(key), total)

    def _maybe_target(self, factor: int, key: int, total: int) -> None:
        if total >= self.eligible_after and len(self.targets) < self.max_targets \
                and (factor, key) not in self._target_set:
            self.targets.append((factor, key))
            self._target_set.add((factor, key))

    def counts(self, graphs: np.ndarray) -> np.ndarray:
        """Sightings so far of each row of ``graphs [B, N, N + 1]``: int64 ``[B, N]`` (0: never seen)."""
        keys = row_keys(graphs)
        out = np.zeros(keys.shape, dtype=np.int64)
        for j in range(self.num_factors):
            get = self._counts[j].get
            out[:, j] = [get(int(k), 0) for k in keys[:, j]]
        return out

    def count(self, factor: int, key: int) -> int:
        return self._counts[factor].get(key, 0)

    def seen(self) -> int:
        """Distinct rows seen, over all factors."""
        return sum(len(c) for c in self._counts)

    def target_arrays(self, width: int) -> tuple[np.ndarray, np.ndarray]:
        """The targets as ``factors [T]`` int64 and ``rows [T, width]`` bool."""
        if not self.targets:
            return np.zeros(0, dtype=np.int64), np.zeros((0, width), dtype=bool)
        factors, keys = map(np.array, zip(*self.targets))
        return factors.astype(np.int64), key_rows(keys, width)

    def state_dict(self) -> dict:
        return {"counts": [dict(c) for c in self._counts], "targets": list(self.targets)}

    def load_state_dict(self, state: dict) -> None:
        self._counts = [dict(c) for c in state["counts"]]
        self.targets = [tuple(t) for t in state["targets"]]
        self._target_set = set(self.targets)


def novelty_reward(counts: np.ndarray) -> np.ndarray:
    """Eq. 6.1: ``count(G)^(-1/2)`` per induced row (counts ``[...]``, taken after the update, so >= 1),
    summed over the factors of a step (``[B, N] -> [B]``)."""
    return (1.0 / np.sqrt(np.maximum(counts, 1))).sum(axis=-1)


def graph_matches(induced: np.ndarray, factor: np.ndarray, row: np.ndarray) -> np.ndarray:
    """``1[induced row of factor = target row]``: induced ``[B, N, N + 1]``, factor ``[B]``, row ``[B, N + 1]``."""
    picked = induced[np.arange(len(factor)), factor]
    return (picked == row).all(axis=-1)


def skill_reward(induced: np.ndarray, factor: np.ndarray, row: np.ndarray, log_q: np.ndarray,
                 diversity_weight: float) -> np.ndarray:
    """Eq. 6.2: ``1[induced = G] * (1 + lambda_b * log q(b | s', G))``, float32 ``[B]``.

    ``log q`` is floored at ``-1 / lambda_b`` so that inducing the target never pays less than
    missing it (the chapter's formula can go negative for a discriminator that is sure of another b)."""
    match = graph_matches(induced, factor, row)
    floor = -1.0 / diversity_weight if diversity_weight > 0 else -np.inf
    diversity = diversity_weight * np.maximum(np.asarray(log_q, dtype=np.float64), floor)
    return (match * (1.0 + diversity)).astype(np.float32)


def hindsight_relabel(induced: np.ndarray, factor: np.ndarray, row: np.ndarray, counts: np.ndarray,
                      fraction: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Relabel ``fraction`` of the samples to a row of ``induced``: the factor drawn with weights
    ``count^(-1/2)`` of its induced row (rarely seen rows preferred), its induced row the new target.

    ``induced`` and ``counts`` are the graphs achieved where the new targets come from: the samples'
    own steps, or (HER's "future" strategy) a later step of each sample's episode, in which case the
    reward is still computed from the sample's own induced graph (:func:`skill_reward`).

    Returns ``(factor', row', relabelled [B] bool)``; rows not relabelled keep their labels."""
    b, n = counts.shape
    relabelled = rng.random(b) < fraction
    weights = 1.0 / np.sqrt(np.maximum(counts, 1))
    cdf = np.cumsum(weights / weights.sum(axis=1, keepdims=True), axis=1)
    drawn = np.minimum((cdf < rng.random((b, 1))).sum(axis=1), n - 1)
    new_factor = np.where(relabelled, drawn, factor)
    new_row = np.where(relabelled[:, None], induced[np.arange(b), new_factor], row)
    return new_factor.astype(np.int64), new_row, relabelled


def target_features(factor: torch.Tensor, row: torch.Tensor, num_factors: int) -> torch.Tensor:
    """A target ``G`` as network input: the factor one-hot and the row's bits, ``[B, 2N + 1]``."""
    return torch.cat([F.one_hot(factor, num_factors).float(), row.float()], dim=1)


class DiversityDiscriminator(nn.Module):
    """DIAYN's ``q(b | s, G)``: an MLP over the state's features and the target, K logits."""

    def __init__(self, state_features: int, num_factors: int, k: int, hidden: int = 64) -> None:
        super().__init__()
        self.num_factors = num_factors
        self.net = nn.Sequential(nn.Linear(state_features + 2 * num_factors + 1, hidden), nn.ReLU(),
                                 nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, k))

    def forward(self, features: torch.Tensor, factor: torch.Tensor, row: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([features, target_features(factor, row, self.num_factors)], dim=1))

    def log_prob(self, features: torch.Tensor, factor: torch.Tensor, row: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``log q(b | s, G)`` per sample, ``[B]``."""
        return self(features, factor, row).log_softmax(-1).gather(1, b[:, None]).squeeze(1)

    def loss(self, features: torch.Tensor, factor: torch.Tensor, row: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Cross-entropy of the true diversity index (Algorithm 7, line 16)."""
        return F.cross_entropy(self(features, factor, row), b)
