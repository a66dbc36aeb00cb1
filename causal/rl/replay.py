"""A uniform ring buffer of (obs, action, reward, next obs, terminated) for off-policy agents.

``causal.replay.ReplayBuffer`` keeps only (state, action, next state) for dynamics learning; an
off-policy agent also needs rewards and termination, hence this one.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from causal.rl.base import ReplayBatch

_NAMES = ("obs", "actions", "rewards", "next_obs", "terminated")


class UniformReplay:
    """The oldest rows are overwritten once ``capacity`` is reached; sampling is uniform."""

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, seed: int = 0) -> None:
        self.capacity = capacity
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.actions = np.zeros((capacity, action_dim), np.float32)
        self.rewards = np.zeros(capacity, np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.terminated = np.zeros(capacity, np.float32)
        self.size, self.cursor = 0, 0
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, next_obs: np.ndarray,
            terminated: np.ndarray) -> None:
        """Append a batch of rows (leading dimension = rows)."""
        rows = [np.asarray(a, np.float32) for a in (obs, actions, rewards, next_obs, terminated)]
        n = min(len(rows[0]), self.capacity)
        rows = [a[-n:] for a in rows]
        index = (self.cursor + np.arange(n)) % self.capacity
        for store, values in zip(self._stores(), rows):
            store[index] = values.reshape(store[index].shape)
        self.cursor = int((self.cursor + n) % self.capacity)
        self.size = min(self.capacity, self.size + n)

    def sample(self, batch_size: int) -> ReplayBatch:
        """``batch_size`` rows drawn uniformly with replacement."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        index = self.rng.integers(0, self.size, batch_size)
        return ReplayBatch(*(torch.from_numpy(store[index]) for store in self._stores()))

    def _stores(self) -> tuple[np.ndarray, ...]:
        return self.obs, self.actions, self.rewards, self.next_obs, self.terminated

    def state_dict(self) -> dict[str, Any]:
        """Stored rows, cursor and sampling generator state (plain ints: loads with weights_only)."""
        state: dict[str, Any] = {n: torch.from_numpy(s[: self.size].copy()) for n, s in zip(_NAMES, self._stores())}
        state["cursor"] = self.cursor
        state["rng"] = self.rng.bit_generator.state
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        n = min(int(state["obs"].shape[0]), self.capacity)
        for name, store in zip(_NAMES, self._stores()):
            store[:n] = state[name][:n].numpy()
        self.size, self.cursor = n, int(state["cursor"]) % self.capacity
        self.rng.bit_generator.state = state["rng"]
