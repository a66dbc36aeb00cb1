"""Demonstration datasets of a scripted expert, recorded as frames (FLAM's behaviour cloning, Table 8.4)."""
from __future__ import annotations

from typing import Callable

import gymnasium as gym
import numpy as np


def record_demonstrations(env: gym.Env, transitions: int, seed: int, epsilon: float,
                          expert: Callable[[gym.Env], int],
                          scene: Callable[[gym.Env], tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """At least ``transitions`` steps of ``expert(env)`` (the action it takes in the env's current
    state), a uniformly random action of ``env.action_space`` instead with probability ``epsilon``;
    whole episodes, reset with seeds ``seed, seed + 1, ...``, choices from
    ``numpy.random.default_rng(seed)``. ``scene(env)`` is the current frame and its labels.

    ``frames`` uint8 ``[F, H, W, 3]`` and ``labels`` uint8 ``[F, H, W]`` of every frame, episodes one
    after another (an episode of L steps has L + 1 frames); per transition ``current`` (int64: the
    index of its first frame; the next frame is ``current + 1``), ``actions`` (int64) and ``episode``
    (int64); per episode ``returns`` (float64)."""
    if transitions < 1 or not 0.0 <= epsilon <= 1.0:
        raise ValueError(f"transitions must be >= 1 and epsilon in [0, 1], got {transitions}, {epsilon}")
    rng = np.random.default_rng(seed)
    num_actions = int(env.action_space.n)
    frames, labels, current, actions, episode_of, returns = [], [], [], [], [], []
    while len(actions) < transitions:
        env.reset(seed=seed + len(returns))
        total, done = 0.0, False
        while True:
            frame, label = scene(env)
            frames.append(frame)
            labels.append(label)
            if done:
                break
            action = int(rng.integers(num_actions)) if rng.random() < epsilon else int(expert(env))
            current.append(len(frames) - 1)
            actions.append(action)
            episode_of.append(len(returns))
            _, reward, terminated, truncated, _ = env.step(action)
            total += reward
            done = terminated or truncated
        returns.append(total)
    return {"frames": np.stack(frames), "labels": np.stack(labels), "current": np.asarray(current, np.int64),
            "actions": np.asarray(actions, np.int64), "episode": np.asarray(episode_of, np.int64),
            "returns": np.asarray(returns, np.float64)}
