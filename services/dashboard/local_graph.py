"""dashboard local graphs: a LocalGraphReport as the page draws it, and its scores over the run.

Pure, like ``core.py``. Each example transition becomes four matrices [d_S][d_S + 1]: the
estimator's ``scores``, the edges it ``predicted`` (score >= the report's threshold, self-edges
always), the ``truth`` and each entry's ``outcome`` (tp / fp / fn / tn, "self" on the diagonal).
Parallel matrices rather than a dict per cell keep a pushed snapshot small.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from proto.messages import LocalGraphReport
from services.dashboard.cells import cause_names, classify, count_outcomes, short

LOCAL_CURVE_METRICS = ("roc_auc", "pr_auc", "best_f1", "f1", "precision", "recall", "positive_rate")


@dataclass(frozen=True)
class LocalPoint:
    """One local report's pooled scores on the local learning curve (None where it lacks one)."""

    time: float
    env_steps: int
    updates: int
    roc_auc: float | None
    pr_auc: float | None
    best_f1: float | None
    f1: float | None
    """At the report's threshold, as ``precision`` and ``recall``."""
    precision: float | None
    recall: float | None
    positive_rate: float | None
    """Share of true edges among the scored entries: PR AUC's chance level."""

    @classmethod
    def of(cls, report: LocalGraphReport, time: float) -> LocalPoint:
        scores = {name: short(report.metrics[name]) if name in report.metrics else None
                  for name in LOCAL_CURVE_METRICS}
        return cls(time=time, env_steps=report.env_steps, updates=report.updates, **scores)


def local_graph_document(report: LocalGraphReport, received_at: float, history: list[LocalPoint],
                         max_examples: int) -> dict:
    """The latest local report (its first ``max_examples`` example transitions) and the score history."""
    shown = min(report.scores.shape[0], max_examples)
    examples = [example_document(report.scores[k], report.truth[k], report.threshold) for k in range(shown)]
    score_max = float(report.scores[:shown].max()) if shown else report.threshold
    return {"kind": report.kind, "estimator": report.estimator, "weights_version": report.weights_version,
            "env_steps": report.env_steps, "updates": report.updates, "num_transitions": report.num_transitions,
            "timestamp": report.timestamp, "received_at": received_at, "threshold": report.threshold,
            "factor_names": list(report.factor_names), "cause_names": cause_names(report.factor_names),
            "metrics": {name: short(value) for name, value in report.metrics.items()},
            "score_max": short(score_max), "num_examples": int(report.scores.shape[0]), "examples": examples,
            "history": [asdict(p) for p in history]}


def example_document(scores: np.ndarray, truth: np.ndarray, threshold: float) -> dict:
    """One transition's [d_S, d_S + 1] scores against its true local graph."""
    predicted = predicted_graph(scores, threshold)
    outcomes = classify(predicted, truth)
    return {"scores": [[short(v) for v in row] for row in scores], "predicted": predicted.tolist(),
            "truth": truth.astype(np.uint8).tolist(), "outcomes": outcomes, "confusion": count_outcomes(outcomes)}


def predicted_graph(scores: np.ndarray, threshold: float) -> np.ndarray:
    """0/1 [d_S, d_S + 1]: an edge where the score reaches ``threshold``; self-edges always."""
    predicted = (scores >= threshold).astype(np.uint8)
    d = scores.shape[0]
    predicted[np.arange(d), np.arange(d)] = 1
    return predicted
