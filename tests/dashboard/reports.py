"""Reports built for the dashboard tests: a Chemical-like factor set, a true graph, a noisy learned one,
and local-graph reports of example transitions whose true local graphs are subsets of that graph."""
from __future__ import annotations

import time

import numpy as np

from causal.abstraction import cdl_abstraction
from causal.graph_metrics import score_graph, score_local_graphs, scored_entries
from proto.messages import GraphReport, LocalGraphReport, ServiceStats

THRESHOLD = 0.02


def factor_names(num_objects: int) -> tuple[str, ...]:
    return tuple(f"obj{k}.{part}" for k in range(num_objects) for part in ("color", "x", "y"))


def true_graph(num_objects: int) -> np.ndarray:
    """The action sets colours; each colour depends on the previous object's colour and, for even objects, on x."""
    n = 3 * num_objects
    truth = np.eye(n, n + 1, dtype=np.uint8)
    for k in range(num_objects):
        truth[3 * k, n] = 1
        if k:
            truth[3 * k, 3 * (k - 1)] = 1
        if k % 2 == 0:
            truth[3 * k, 3 * k + 1] = 1
    return truth


def make_report(num_objects: int = 3, version: int = 1, errors: int = 2, seed: int = 0, kind: str = "cdl",
                with_truth: bool = True) -> GraphReport:
    """A report whose learned graph gets ``errors`` scored cells wrong (alternately FP and FN)."""
    rng = np.random.default_rng(seed)
    truth = true_graph(num_objects)
    n = truth.shape[0]
    cmi = np.where(truth == 1, rng.uniform(0.05, 0.8, truth.shape), rng.uniform(1e-4, 0.008, truth.shape))
    scored = np.argwhere(scored_entries(truth.shape))
    positives = [tuple(c) for c in scored if truth[tuple(c)]]
    negatives = [tuple(c) for c in scored if not truth[tuple(c)]]
    for e in range(errors):
        pool = negatives if e % 2 == 0 else positives
        cell = pool[int(rng.integers(len(pool)))]
        cmi[cell] = rng.uniform(0.03, 0.1) if e % 2 == 0 else rng.uniform(1e-3, 0.01)
    cmi = cmi.astype(np.float32)
    adjacency = (cmi >= THRESHOLD).astype(np.uint8)
    adjacency[np.arange(n), np.arange(n)] = 1  # self-edges are always kept (Assumption 4)
    abstraction = cdl_abstraction(adjacency)
    steps = 5_000 * version
    return GraphReport(kind=kind, weights_version=version, env_steps=steps, updates=steps // 20,
                       factor_names=factor_names(num_objects), cmi=cmi, adjacency=adjacency, threshold=THRESHOLD,
                       controllable=abstraction.controllable, action_relevant=abstraction.action_relevant,
                       action_irrelevant=abstraction.action_irrelevant,
                       metrics=score_graph(cmi, truth, THRESHOLD) if with_truth else {},
                       true_graph=truth if with_truth else None, num_heldout=400 + n, timestamp=time.time())


def make_local_report(num_objects: int = 3, version: int = 1, examples: int = 4, errors: int = 2, seed: int = 0,
                      kind: str = "cdl", estimator: str = "pcmi") -> LocalGraphReport:
    """Local graphs of ``examples`` transitions, each keeping about 70% of the global graph's edges; the
    pCMI-like scores (nats) get ``errors`` scored entries of every transition wrong (alternately FP, FN)."""
    rng = np.random.default_rng(seed)
    shape = (examples, *true_graph(num_objects).shape)
    truth = (true_graph(num_objects) * (rng.random(shape) < 0.7)).astype(np.uint8)
    n = shape[1]
    truth[:, np.arange(n), np.arange(n)] = 1
    scores = np.where(truth == 1, rng.uniform(0.05, 1.5, shape), rng.uniform(-0.01, 0.008, shape))
    scored = np.argwhere(scored_entries(shape[1:]))
    for k in range(examples):
        for e in range(errors):
            pool = [tuple(c) for c in scored if truth[(k, *c)] == e % 2]
            if pool:
                cell = (k, *pool[int(rng.integers(len(pool)))])
                scores[cell] = rng.uniform(0.03, 0.1) if e % 2 == 0 else rng.uniform(1e-3, 0.01)
    scores = scores.astype(np.float32)
    steps = 5_000 * version
    return LocalGraphReport(kind=kind, estimator=estimator, weights_version=version, env_steps=steps,
                            updates=steps // 20, factor_names=factor_names(num_objects), threshold=THRESHOLD,
                            scores=scores, truth=truth, metrics=score_local_graphs(scores, truth, THRESHOLD),
                            num_transitions=256, timestamp=time.time())


def make_stats(service: str, instance: str = "0", **values: float) -> ServiceStats:
    return ServiceStats(service=service, instance=instance, values=dict(values), timestamp=time.time())


def true_reward_parents(num_objects: int) -> np.ndarray:
    """The reward reads the colours and the action (a Match-like task)."""
    parents = np.zeros(3 * num_objects + 1, np.uint8)
    parents[0 : 3 * num_objects : 3] = 1
    parents[-1] = 1
    return parents


def make_reward_report(num_objects: int = 3, version: int = 1, errors: int = 2, reward_errors: int = 1,
                       seed: int = 0, kind: str = "cbm") -> GraphReport:
    """:func:`make_report` with a causal reward model's graph (CBM): the first ``reward_errors`` positions
    (obj0.x, obj0.y, ...) taken for reward parents, the minimal abstraction and its scores."""
    from dataclasses import replace

    from causal.abstraction import abstraction_accuracy, minimal_abstraction
    from causal.graph_metrics import binary_scores

    report = make_report(num_objects, version, errors, seed, kind)
    truth = true_reward_parents(num_objects)
    scores = np.where(truth == 1, 0.4, 0.001).astype(np.float32)
    wrong = [k for k in range(3 * num_objects) if k % 3][:reward_errors]
    scores[wrong] = 0.05
    parents = (scores >= 0.01).astype(np.uint8)
    abstraction = minimal_abstraction(report.adjacency, parents)
    n = 3 * num_objects
    true_kept = minimal_abstraction(report.true_graph, truth).kept
    metrics = {**report.metrics, **{f"reward_{k}": v for k, v in binary_scores(parents, truth, np.ones(n + 1, bool)).items()},
               "abstraction_accuracy": abstraction_accuracy(abstraction.kept, true_kept, n),
               "abstraction_accuracy_true_reward": 1.0}
    return replace(report, controllable=abstraction.controllable, action_relevant=abstraction.action_relevant,
                   action_irrelevant=abstraction.action_irrelevant, metrics=metrics, reward_scores=scores,
                   reward_parents=parents, reward_threshold=0.01, true_reward_parents=truth)
