"""Scores of a reward graph and of the task abstraction built from it (chapter 4), against the truth.

Pure functions of arrays: the graph-evaluator's core calls them for a method with a reward graph. The
reward's parents are a ``[d_S + 1]`` vector (factors at t, the action last); the true minimal
abstraction is Theorem 4.1's on the env's true graph and true reward parents.
"""
from __future__ import annotations

import numpy as np

from causal.abstraction import Abstraction, abstraction_accuracy, minimal_abstraction
from causal.graph_metrics import binary_scores, roc_auc


def reward_metrics(scores: np.ndarray, parents: np.ndarray, truth: np.ndarray | None) -> dict[str, float]:
    """``reward_accuracy``, ``reward_precision``, ``reward_recall``, ``reward_f1`` of the learned parents and
    ``reward_roc_auc`` of the scores, over every entry (the action included); none without a truth."""
    if truth is None:
        return {}
    every = np.ones(truth.shape, dtype=bool)
    out = {f"reward_{k}": v for k, v in binary_scores(parents.astype(bool), truth, every).items()}
    out["reward_roc_auc"] = roc_auc(scores, truth, every)
    return out


def abstraction_metrics(adjacency: np.ndarray, abstraction: Abstraction, true_graph: np.ndarray | None,
                        true_reward_parents: np.ndarray | None) -> dict[str, float]:
    """``abstraction_accuracy``: share of factors the learned abstraction keeps or drops as the true minimal
    one does; ``abstraction_accuracy_true_reward``: the same for the learned graph with the true reward
    parents (Table 4.1's setting); ``abstraction_kept`` and ``true_abstraction_kept``: factor counts.
    None without both truths."""
    if true_graph is None or true_reward_parents is None:
        return {}
    n = adjacency.shape[0]
    truth = minimal_abstraction(true_graph, true_reward_parents).kept
    with_true_reward = minimal_abstraction(adjacency, true_reward_parents).kept
    return {"abstraction_accuracy": abstraction_accuracy(abstraction.kept, truth, n),
            "abstraction_accuracy_true_reward": abstraction_accuracy(with_true_reward, truth, n),
            "abstraction_kept": float(len(abstraction.kept)), "true_abstraction_kept": float(len(truth))}
