"""Behaviour cloning from FLAM's pseudo-labels (dissertation chapter 8, eq. 8.7 and Table 8.4).

With a few action labels an action decoder ``M_a`` learns to map latent actions alpha to real actions;
applied to the latent actions of a large unlabelled video dataset it gives pseudo-labels, on which a
policy is cloned:

    L_pi = E_{(o, alpha) ~ D} || pi(o) - M_a(alpha) ||                        (eq. 8.7)

Our actions are discrete, so ``M_a`` is a classifier and the policy is trained by cross-entropy on
``M_a``'s most likely action (the discrete form of eq. 8.7's regression; docs/deviations.md). The
policy is a small convolutional network on one frame; the vanilla BC baseline is the same network on
the labelled subset alone (the chapter's comparison: the same architecture and training setup).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from causal.slots import frames_to_tensor


@dataclass(frozen=True)
class ClassifierTraining:
    """Adam on a classifier's cross-entropy: updates, batch, learning rate and weight decay."""

    updates: int = 2000
    batch_size: int = 128
    lr: float = 1e-3
    weight_decay: float = 1e-4

    def __post_init__(self) -> None:
        if min(self.updates, self.batch_size) < 1 or not self.lr > 0 or self.weight_decay < 0:
            raise ValueError("updates and batch_size must be positive, lr > 0 and weight_decay >= 0")


class ActionDecoder(nn.Module):
    """``M_a``: action logits from a flat input (latent actions ``[B, K * d_a]`` or, for the plain
    inverse-dynamics baseline, a transition's features), standardised by the labelled inputs' moments."""

    def __init__(self, input_dim: int, num_actions: int, hidden: int = 128) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(input_dim))
        self.register_buffer("scale", torch.ones(input_dim))
        self.net = nn.Sequential(nn.Linear(input_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, num_actions))

    def fit_moments(self, inputs: torch.Tensor) -> None:
        self.mean.copy_(inputs.mean(0))
        self.scale.copy_(inputs.std(0).clamp_min(1e-6))

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.net((inputs - self.mean) / self.scale)


class FramePolicy(nn.Module):
    """pi(o): action logits from one RGB frame (uint8 ``[B, H, W, 3]``, H = W = 32 or 64)."""

    def __init__(self, num_actions: int, frame_size: int = 32, width: int = 32) -> None:
        super().__init__()
        cells = frame_size // 4
        self.net = nn.Sequential(nn.Conv2d(3, width // 2, 3, stride=2, padding=1), nn.ReLU(),
                                 nn.Conv2d(width // 2, width, 3, stride=2, padding=1), nn.ReLU(), nn.Flatten(),
                                 nn.Linear(width * cells * cells, 128), nn.ReLU(), nn.Linear(128, num_actions))

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return self.net(frames_to_tensor(frames))


def fit_classifier(model: nn.Module, inputs: torch.Tensor, targets: torch.Tensor, training: ClassifierTraining,
                   seed: int = 0) -> float:
    """Cross-entropy on random minibatches of ``(inputs, targets)`` (int64 ``[N]``); the last loss.
    Leaves the model in eval mode."""
    if len(inputs) != len(targets) or len(inputs) == 0:
        raise ValueError(f"need as many targets as inputs, and at least one: {len(inputs)} vs {len(targets)}")
    generator = torch.Generator().manual_seed(seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=training.lr, weight_decay=training.weight_decay)
    model.train()
    loss = torch.tensor(float("nan"))
    for _ in range(training.updates):
        batch = torch.randint(len(inputs), (training.batch_size,), generator=generator)
        loss = F.cross_entropy(model(inputs[batch]), targets[batch])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    model.eval()
    return float(loss.detach())


@torch.no_grad()
def predict(model: nn.Module, inputs: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """The most likely class of every input (int64 ``[N]``), in chunks."""
    model.eval()
    return torch.cat([model(inputs[i:i + chunk]).argmax(-1) for i in range(0, len(inputs), chunk)])


def pseudo_labels(decoder: ActionDecoder, inputs: torch.Tensor, labelled: torch.Tensor, actions: torch.Tensor,
                  training: ClassifierTraining, seed: int = 0) -> tuple[torch.Tensor, float]:
    """Fit ``M_a`` on the labelled rows (``labelled`` int64 indices into ``inputs`` and ``actions``), then
    label every row; returns the pseudo-labels and their accuracy on the rows not labelled (NaN when
    every row is labelled)."""
    decoder.fit_moments(inputs[labelled])
    fit_classifier(decoder, inputs[labelled], actions[labelled], training, seed=seed)
    labels = predict(decoder, inputs)
    unlabelled = torch.ones(len(inputs), dtype=torch.bool)
    unlabelled[labelled] = False
    accuracy = float((labels[unlabelled] == actions[unlabelled]).float().mean()) if unlabelled.any() else float("nan")
    return labels, accuracy


def evaluate_policy(policy: FramePolicy | None, make_env, episodes: int, seed: int,
                    act=None) -> dict[str, float]:
    """Mean episodic return over ``episodes`` episodes of a fresh env (``make_env()``) reset with seeds
    ``seed, seed + 1, ...``: actions sampled from ``policy``'s softmax on the frame (a seeded generator),
    or from ``act(env)`` when given (scripted experts, the random policy)."""
    env = make_env()
    generator = torch.Generator().manual_seed(seed)
    returns, successes = [], 0
    for episode in range(episodes):
        _, info = env.reset(seed=seed + episode)
        total, done = 0.0, False
        while not done:
            if act is not None:
                action = int(act(env))
            else:
                with torch.no_grad():
                    logits = policy(torch.from_numpy(info["frame"])[None])
                action = int(torch.multinomial(F.softmax(logits[0], -1), 1, generator=generator))
            _, reward, terminated, truncated, info = env.step(action)
            total += reward
            done = terminated or truncated
        returns.append(total)
        successes += bool(info.get("success", False))
    values = np.asarray(returns)
    return {"return_mean": float(values.mean()), "return_std": float(values.std()),
            "success_rate": successes / episodes, "episodes": episodes}
