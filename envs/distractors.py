"""Chapter 4's distractor factors, built from the text (the authors' released code lacks them).

"20 factors whose values are random projections of the action are added to the state space [...]
20 uncontrollable distractors whose values are uniformly sampled from [-1, 1]. The distractors have
no interaction with other state factors." (section 4.3.) From that:

* a **controllable distractor** ``cd.k`` takes, at every step, the value ``P_k . a_t`` of a fixed
  random projection of the action just taken (one-hot for a discrete action): its only parent is
  the action (its own previous value is overwritten; the truth keeps the self-edge every factor has
  by Assumption 4, which is never scored). It starts at 0;
* an **uncontrollable distractor** ``ud.k`` is drawn from U(-1, 1) at every step (and at reset): it
  has no parent but itself (Assumption 4 again);
* neither is a parent of any other factor, nor of the reward.

So the true graph of an environment with distractors is its own graph with these rows and columns
added (:meth:`Distractors.extend_graph`), and its true minimal task abstraction never keeps one. The
projection is fixed by ``seed`` (the same for every worker), its rows scaled so every value lies in
[-1, 1] for actions in [-1, 1].

For out-of-distribution evaluation (Fig. 4.8), ``ood_range = (lo, hi)`` lifts every value ``v`` out of
its training range [-1, 1] to ``sign(v) (lo + (hi - lo) |v|)`` (``sign(0) = +1``): uncontrollable values
become uniform on [-hi, -lo] u [lo, hi], controllable ones stay a function of the action alone (same
parents) but never seen in training. The random draws are the same with and without it, so the same
seed gives the same episode, lifted.
"""
from __future__ import annotations

import numpy as np

CONTROLLABLE, UNCONTROLLABLE = "cd", "ud"
"""Object names of the two kinds (factor ``cd.3`` is controllable distractor 3)."""


def parse_distractors(text: str) -> tuple[int, int]:
    """``"20,20"`` -> (controllable, uncontrollable) counts; ``ValueError`` for anything else."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        raise ValueError(f"distractors must be 'controllable,uncontrollable' counts like '20,20', got {text!r}")
    counts = int(parts[0]), int(parts[1])
    if max(counts) > 256:
        raise ValueError(f"at most 256 distractors of each kind, got {text!r}")
    return counts


def is_distractor(name: str) -> bool:
    """Whether factor ``name`` is a distractor (of either kind)."""
    return name.split(".", 1)[0] in (CONTROLLABLE, UNCONTROLLABLE)


class Distractors:
    """Values, names, bounds and ground truth of ``controllable`` + ``uncontrollable`` distractors for an
    environment whose action is ``action_kind`` (``"categorical"`` of ``action_size`` choices, or a
    ``"continuous"`` vector of ``action_size`` entries in [-1, 1])."""

    def __init__(self, controllable: int, uncontrollable: int, action_kind: str, action_size: int,
                 seed: int = 0, ood_range: tuple[float, float] | None = None) -> None:
        if ood_range is not None and not 1.0 <= ood_range[0] < ood_range[1]:
            raise ValueError(f"ood_range must be (lo, hi) with 1 <= lo < hi, got {ood_range}")
        self.controllable, self.uncontrollable = controllable, uncontrollable
        self.ood_range = None if ood_range is None else (float(ood_range[0]), float(ood_range[1]))
        self.action_kind = action_kind
        rng = np.random.default_rng(seed)
        projection = rng.uniform(-1.0, 1.0, size=(controllable, action_size))
        if action_kind == "continuous":  # |P_k . a| <= ||P_k||_1 for a in [-1, 1]^D
            projection /= np.maximum(np.abs(projection).sum(axis=1, keepdims=True), 1e-12)
        self.projection = projection

    @property
    def count(self) -> int:
        return self.controllable + self.uncontrollable

    @property
    def names(self) -> tuple[str, ...]:
        return (tuple(f"{CONTROLLABLE}.{k}" for k in range(self.controllable))
                + tuple(f"{UNCONTROLLABLE}.{k}" for k in range(self.uncontrollable)))

    @property
    def objects(self) -> tuple[str, ...]:
        return (CONTROLLABLE,) * self.controllable + (UNCONTROLLABLE,) * self.uncontrollable

    def reset(self, rng: np.random.Generator) -> np.ndarray:
        """Values at the start of an episode: controllable 0, uncontrollable fresh draws."""
        return self.lift(np.concatenate([np.zeros(self.controllable), rng.uniform(-1.0, 1.0, self.uncontrollable)]))

    def step(self, action: np.ndarray | int, rng: np.random.Generator) -> np.ndarray:
        """Values after taking ``action``: the action's projections, then fresh uniform draws."""
        return self.lift(np.concatenate([self.project(action), rng.uniform(-1.0, 1.0, self.uncontrollable)]))

    @property
    def bound(self) -> float:
        """The largest absolute value a distractor takes: 1, or ``hi`` out of distribution."""
        return 1.0 if self.ood_range is None else self.ood_range[1]

    def lift(self, values: np.ndarray) -> np.ndarray:
        """In-range ``values`` as they are, or lifted into ``ood_range`` (see the module docstring)."""
        if self.ood_range is None:
            return values
        lo, hi = self.ood_range
        return np.where(values < 0, -1.0, 1.0) * (lo + (hi - lo) * np.abs(values))

    def project(self, action: np.ndarray | int) -> np.ndarray:
        """``P a``: a column of ``P`` for a discrete action, the matrix product for a continuous one."""
        if self.action_kind == "categorical":
            return self.projection[:, int(action)].copy()
        return self.projection @ np.asarray(action, dtype=np.float64).reshape(-1)

    def extend_graph(self, graph: np.ndarray) -> np.ndarray:
        """A ``[d, d + 1]`` graph -> ``[d + m, d + m + 1]`` with the distractors appended (action last):
        controllable ones read the action, every distractor keeps its self-edge, nothing else changes."""
        d, m = graph.shape[0], self.count
        out = np.zeros((d + m, d + m + 1), dtype=graph.dtype)
        out[:d, :d] = graph[:, :d]
        out[:d, -1] = graph[:, d]
        out[np.arange(d, d + m), np.arange(d, d + m)] = 1
        out[d : d + self.controllable, -1] = 1
        return out

    def extend_parents(self, parents: np.ndarray) -> np.ndarray:
        """A ``[d + 1]`` parent vector (the reward's; action last) -> ``[d + m + 1]``: no distractor is a parent."""
        d = parents.shape[0] - 1
        return np.concatenate([parents[:d], np.zeros(self.count, parents.dtype), parents[d:]])
