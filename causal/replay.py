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
