"""Live local-graph scoring (issue 17, chapter 5's evaluation): the method's local-graph estimator
on held-out transitions that carry the simulator's true local graphs. No bus.

Scores pool every off-diagonal entry of every sampled transition (``causal.graph_metrics.
score_local_graphs``): ROC AUC, PR AUC, the best F1 over thresholds, and F1 at the estimator's own
threshold. The chapter's evaluation code also reports a mean over entries whose labels vary; we
report the pooled figure only (docs/scoring.md).
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch
from torch import nn

from causal.graph_metrics import score_local_graphs, scored_entries
from causal.method import LocalGraphEstimator
from causal.replay import LabelledReplay
from proto.messages import EnvSpec, LocalGraphReport, TransitionBatch, Weights


CHUNK = 1_000
"""Transitions per call of the local-graph estimator."""


class LocalGraphScorer:
    """A ring of held-out transitions with their true local graphs, and scoring on a sample of it."""

    def __init__(self, spec: EnvSpec, estimator: LocalGraphEstimator, kind: str, capacity: int, samples: int,
                 examples: int, seed: int, device: torch.device = torch.device("cpu")) -> None:
        self.spec, self.estimator, self.kind, self.device = spec, estimator, kind, device
        self.samples, self.examples = samples, examples
        self.ring = LabelledReplay(capacity, spec.state_dim, spec.action_dim, spec.num_factors, seed=seed)
        self.evaluated_version = -1
        self.history: list[dict[str, float]] = []

    def add(self, batch: TransitionBatch, keep: np.ndarray) -> int:
        """Keep the held-out rows (``keep``) of a batch that carries true local graphs."""
        if batch.local_graph is None or not keep.any():
            return 0
        self.ring.add_labelled(batch.state[keep], batch.action[keep], batch.next_state[keep], batch.local_graph[keep])
        return int(keep.sum())

    def due(self, weights: Weights | None, min_transitions: int) -> bool:
        return weights is not None and weights.version > self.evaluated_version and self.ring.size >= min_transitions

    def evaluate(self, model: nn.Module, weights: Weights, every: bool = False,
                 progress: Callable[[int, int], None] | None = None) -> LocalGraphReport:
        """Score ``samples`` random held-out transitions (``every``: all of them, for the final report).

        The estimator runs on :data:`CHUNK` transitions at a time (a transition's local graph is its
        own, so the scores are those of one call on all of them) and ``progress(done, total)`` is called
        after each chunk: the final report of an expensive estimator (ELDEN's Jacobians, ~20 ms a
        transition on Thawing) takes minutes and a bounded amount of memory."""
        n = self.ring.size if every else min(self.samples, self.ring.size)
        index = np.sort(self.ring.rng.choice(self.ring.size, n, replace=False))
        state, action, next_state, truth = self.ring.rows(index)
        parts = []
        for start in range(0, n, CHUNK):
            rows = (t[start:start + CHUNK].to(self.device) for t in (state, action, next_state))
            parts.append(np.asarray(self.estimator.scores(model, *rows), dtype=np.float32))
            if progress is not None:
                progress(min(start + CHUNK, n), n)
        scores = np.concatenate(parts)
        threshold = float(self.estimator.threshold(model))
        metrics = score_local_graphs(scores, truth, threshold)
        self.evaluated_version = weights.version
        self.history.append({"env_steps": weights.env_steps, "updates": weights.updates, "time": time.time(),
                             **{f"local_{k}": v for k, v in metrics.items()}})
        shown = self._examples(truth)
        return LocalGraphReport(kind=self.kind, estimator=self.estimator.name, weights_version=weights.version,
                                env_steps=weights.env_steps, updates=weights.updates,
                                factor_names=self.spec.factor_names, threshold=threshold,
                                scores=np.nan_to_num(scores[shown], posinf=1e30, neginf=-1e30),
                                truth=truth[shown].astype(np.uint8), metrics=metrics, num_transitions=n,
                                timestamp=time.time())

    def _examples(self, truth: np.ndarray) -> np.ndarray:
        """Up to ``examples`` sampled transitions to show, those with a true interaction first."""
        interacting = (truth & scored_entries(truth.shape[1:])).any(axis=(1, 2))
        order = np.r_[np.nonzero(interacting)[0], np.nonzero(~interacting)[0]]
        return order[: self.examples]

    def state_dict(self) -> dict:
        return {"ring": self.ring.state_dict(), "evaluated_version": self.evaluated_version}

    def load_state_dict(self, saved: dict) -> None:
        self.ring.load_state_dict(saved["ring"])
        self.evaluated_version = int(saved["evaluated_version"])
