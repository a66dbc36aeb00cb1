"""Bounded transition storage and the training / held-out split shared by learner and evaluator.

The split is by episode (the reference holds out 10% of episodes for CMI), decided by a hash of
(worker id, episode id), so every service that sees a transition agrees on its side without talking.
"""
from __future__ import annotations

import zlib

import numpy as np
import torch


def heldout_mask(worker_id: str, episode_ids: np.ndarray, fraction: float) -> np.ndarray:
    """True where the step belongs to a held-out episode."""
    salt = zlib.crc32(worker_id.encode()) & 0xFFFF
    mixed = (episode_ids.astype(np.uint64) * np.uint64(2654435761) + np.uint64(salt)) % np.uint64(10_000)
    return mixed < np.uint64(round(fraction * 10_000))


class ReplayBuffer:
    """A ring buffer of (state, action, next_state, reward) rows; the oldest rows are overwritten.
    The reward column is kept for methods whose models learn it (a causal reward model); rows added
    without one hold 0."""

    def __init__(self, capacity: int, state_dim: int, action_dim: int, seed: int = 0) -> None:
        self.capacity = capacity
        self.state = np.zeros((capacity, state_dim), np.float32)
        self.action = np.zeros((capacity, action_dim), np.float32)
        self.next_state = np.zeros((capacity, state_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.size, self.cursor, self.added = 0, 0, 0
        self.rng = np.random.default_rng(seed)

    def add(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray,
            reward: np.ndarray | None = None) -> None:
        n = min(len(state), self.capacity)
        reward = np.zeros(len(state), np.float32) if reward is None else reward
        index = (self.cursor + np.arange(n)) % self.capacity
        self.state[index], self.action[index] = state[-n:], action[-n:]
        self.next_state[index], self.reward[index] = next_state[-n:], reward[-n:]
        self.cursor = int((self.cursor + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)
        self.added += n

    def sample(self, batch: int, with_reward: bool = False) -> tuple[torch.Tensor, ...]:
        """``batch`` uniform rows: (state, action, next_state), and the reward ``with_reward``."""
        index = self.rng.integers(0, self.size, batch)
        columns = (self.state, self.action, self.next_state) + ((self.reward,) if with_reward else ())
        return tuple(torch.from_numpy(a[index]) for a in columns)

    def sample_clips(self, batch: int, frames: int, tries: int = 8) -> torch.Tensor:
        """``batch`` clips of ``frames`` consecutive states ``[batch, frames, state_dim]``: the states of
        ``frames - 1`` rows stored one after another, each row's ``next_state`` the next row's ``state``
        (so a clip never spans an episode's end, a held-out episode left out, or the seam between two
        workers' batches), never across the ring's seam between newest and oldest. Windows are drawn
        uniformly and the broken ones rejected, ``tries`` rounds of ``batch`` at most; if fewer than
        ``batch`` are whole, whole ones are repeated. ``ValueError`` where no whole clip is found."""
        length = frames - 1
        if length < 1:
            raise ValueError(f"a clip needs at least 2 frames, got {frames}")
        if self.size < length:
            raise ValueError(f"{frames}-frame clips need {length} stored rows, the replay holds {self.size}")
        oldest = self.cursor if self.size == self.capacity else 0
        found: list[np.ndarray] = []
        for _ in range(tries):
            rows = (oldest + self.rng.integers(0, self.size - length + 1, batch)[:, None] + np.arange(length)) % self.capacity
            whole = np.all(self.next_state[rows[:, :-1]] == self.state[rows[:, 1:]], axis=(1, 2))
            found.extend(rows[whole])
            if len(found) >= batch:
                break
        if not found:
            raise ValueError(f"no run of {length} consecutive transitions in {tries * batch} tries: episodes "
                             f"shorter than {frames} frames, or rows that do not follow each other")
        rows = np.stack(found[:batch]) if len(found) >= batch else np.stack(found)[self.rng.integers(0, len(found), batch)]
        clips = np.concatenate([self.state[rows], self.next_state[rows[:, -1:]]], axis=1)
        return torch.from_numpy(clips)

    def all(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return tuple(torch.from_numpy(a[: self.size]) for a in (self.state, self.action, self.next_state))

    def state_dict(self) -> dict:
        return {"state": torch.from_numpy(self.state[: self.size].copy()),
                "action": torch.from_numpy(self.action[: self.size].copy()),
                "next_state": torch.from_numpy(self.next_state[: self.size].copy()),
                "reward": torch.from_numpy(self.reward[: self.size].copy()),
                "cursor": self.cursor, "added": self.added}

    def load_state_dict(self, saved: dict) -> None:
        """Restore saved rows. A full, wrapped ring saved with a smaller capacity is laid out oldest
        first, so that the new rows are appended after its newest instead of overwriting them."""
        rows, cursor = int(saved["state"].shape[0]), int(saved["cursor"])
        reward = saved["reward"].numpy() if "reward" in saved else np.zeros(rows, np.float32)  # older checkpoints
        arrays = [saved[k].numpy() for k in ("state", "action", "next_state")] + [reward]
        if int(saved["added"]) > rows and rows < self.capacity:
            arrays, cursor = [np.roll(a, -cursor, axis=0) for a in arrays], rows
        n = min(rows, self.capacity)
        for mine, theirs in zip((self.state, self.action, self.next_state, self.reward), arrays):
            mine[:n] = theirs[:n]
        self.size, self.cursor, self.added = n, cursor % self.capacity, int(saved["added"])


class LabelledReplay(ReplayBuffer):
    """A ring of (state, action, next_state) rows, each with its true local graph (uint8 ``[d, d + 1]``)."""

    def __init__(self, capacity: int, state_dim: int, action_dim: int, num_factors: int, seed: int = 0) -> None:
        super().__init__(capacity, state_dim, action_dim, seed)
        self.graphs = np.zeros((capacity, num_factors, num_factors + 1), np.uint8)

    def add_labelled(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray, graphs: np.ndarray) -> None:
        n = min(len(state), self.capacity)
        index = (self.cursor + np.arange(n)) % self.capacity
        self.graphs[index] = graphs[-n:]
        self.add(state, action, next_state)

    def rows(self, index: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray]:
        """Transitions ``index`` (rows below :attr:`size`) with their graphs."""
        return (*(torch.from_numpy(a[index]) for a in (self.state, self.action, self.next_state)), self.graphs[index])

    def state_dict(self) -> dict:
        return {**super().state_dict(), "graphs": torch.from_numpy(self.graphs[: self.size].copy())}

    def load_state_dict(self, saved: dict) -> None:
        rows, cursor, added = int(saved["state"].shape[0]), int(saved["cursor"]), int(saved["added"])
        graphs = saved["graphs"].numpy()
        if added > rows and rows < self.capacity:
            graphs = np.roll(graphs, -cursor, axis=0)
        super().load_state_dict(saved)
        self.graphs[: self.size] = graphs[: self.size]


class SumTree:
    """Priorities of ``capacity`` rows and their partial sums in a complete binary tree (an array:
    node ``k`` has children ``2k`` and ``2k + 1``, the leaves start at :attr:`leaves`). Setting and
    finding are vectorised over rows; the loops run over the tree's levels."""

    def __init__(self, capacity: int) -> None:
        self.leaves = 1 << max(capacity - 1, 1).bit_length()
        self.tree = np.zeros(2 * self.leaves, np.float64)

    @property
    def total(self) -> float:
        return float(self.tree[1])

    def get(self, index: np.ndarray) -> np.ndarray:
        return self.tree[np.asarray(index) + self.leaves]

    def set(self, index: np.ndarray, priorities: np.ndarray) -> None:
        node = np.asarray(index, np.int64) + self.leaves
        self.tree[node] = priorities
        node = np.unique(node // 2)
        while node.size and node[0] >= 1:
            self.tree[node] = self.tree[2 * node] + self.tree[2 * node + 1]
            node = np.unique(node[node > 1] // 2)

    def find(self, mass: np.ndarray) -> np.ndarray:
        """The row under each cumulative ``mass`` in [0, total): row k is found with probability
        priority_k / total when ``mass`` is uniform."""
        node = np.ones(len(mass), np.int64)
        mass = np.asarray(mass, np.float64).copy()
        while node.size and node[0] < self.leaves:
            left = self.tree[2 * node]
            right = mass >= left
            mass = np.where(right, mass - left, mass)
            node = 2 * node + right
        return node - self.leaves


class PrioritisedReplay(ReplayBuffer):
    """A replay ring sampled in proportion to per-row priorities (prioritised experience replay,
    Schaul et al. 2016, as chapter 5 uses it for dynamics learning): a new row gets the largest
    priority given so far, the trainer's reports replace it (:meth:`update_priorities`). Sampling is
    stratified: one row from each of ``batch`` equal slices of the total priority. No importance
    weights: the dynamics model is meant to learn rare transitions faster, not to stay unbiased."""

    def __init__(self, capacity: int, state_dim: int, action_dim: int, seed: int = 0) -> None:
        super().__init__(capacity, state_dim, action_dim, seed)
        self.priorities = SumTree(capacity)
        self.max_priority = 1.0

    def add(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray,
            reward: np.ndarray | None = None) -> None:
        index = (self.cursor + np.arange(min(len(state), self.capacity))) % self.capacity
        super().add(state, action, next_state, reward)
        self.priorities.set(index, np.full(len(index), self.max_priority))

    def sample_indexed(self, batch: int, with_reward: bool = False) -> tuple[np.ndarray, tuple[torch.Tensor, ...]]:
        """``batch`` rows drawn in proportion to their priorities, with their row indices."""
        total = self.priorities.total
        mass = (np.arange(batch) + self.rng.random(batch)) * (total / batch)
        index = np.minimum(self.priorities.find(np.minimum(mass, np.nextafter(total, 0))), self.size - 1)
        columns = (self.state, self.action, self.next_state) + ((self.reward,) if with_reward else ())
        return index, tuple(torch.from_numpy(a[index]) for a in columns)

    def sample(self, batch: int, with_reward: bool = False) -> tuple[torch.Tensor, ...]:
        return self.sample_indexed(batch, with_reward)[1]

    def update_priorities(self, index: np.ndarray, priorities: np.ndarray) -> None:
        """New priorities (positive) for rows ``index`` (as :meth:`sample_indexed` returned them)."""
        priorities = np.asarray(priorities, np.float64)
        if priorities.shape != np.shape(index) or not (np.isfinite(priorities).all() and (priorities > 0).all()):
            raise ValueError("priorities must be positive, finite and one per sampled row")
        self.priorities.set(index, priorities)
        self.max_priority = max(self.max_priority, float(priorities.max()))

    def probabilities(self) -> np.ndarray:
        """Each stored row's chance of being drawn by one uniform mass (its priority over the total)."""
        return self.priorities.get(np.arange(self.size)) / self.priorities.total

    def state_dict(self) -> dict:
        return {**super().state_dict(), "max_priority": self.max_priority,
                "priorities": torch.from_numpy(self.priorities.get(np.arange(self.size)).copy())}

    def load_state_dict(self, saved: dict) -> None:
        """Rows and priorities (a checkpoint without priorities gives every row priority 1)."""
        rows, cursor, added = int(saved["state"].shape[0]), int(saved["cursor"]), int(saved["added"])
        priorities = saved["priorities"].numpy() if "priorities" in saved else np.ones(rows)
        if added > rows and rows < self.capacity:
            priorities = np.roll(priorities, -cursor, axis=0)
        super().load_state_dict(saved)
        self.priorities = SumTree(self.capacity)
        self.priorities.set(np.arange(self.size), priorities[: self.size])
        self.max_priority = float(saved.get("max_priority", 1.0))
