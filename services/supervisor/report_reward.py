"""What a run with a reward graph (CBM, chapter 4) adds to its summary and pictures.

``reward_graph``: the reward's scores per factor and the action, the learned and true parents, and
their scores. ``task_abstraction``: the minimal abstraction (Theorem 4.1) split as Fig. 4.2 (b) draws it
(the reward's parents, their ancestors, the dropped factors), the true one and its accuracy, and CDL's
task-independent abstraction of the same graph for comparison. ``distractors``: on an env with chapter
4's distractors, the graph scores Table 4.1 needs beside each other (accuracy over every entry, an
empty graph's, F1 over the entries that involve no distractor).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from causal.abstraction import cdl_abstraction, minimal_abstraction  # noqa: E402
from causal.graph_metrics import binary_scores, scored_entries  # noqa: E402
from envs.distractors import is_distractor  # noqa: E402
from proto.messages import GraphReport  # noqa: E402
from services.supervisor.rounding import significant  # noqa: E402

REWARD_SCORES = ("accuracy", "precision", "recall", "f1", "roc_auc")


def reward_fields(report: GraphReport) -> dict[str, Any]:
    """``reward_graph``, ``task_abstraction`` and (with distractors) ``distractors`` of a report; empty
    for a report without a reward graph."""
    if report.reward_scores is None:
        return {}
    names = list(report.factor_names)
    causes = names + ["action"]
    m = report.metrics
    out: dict[str, Any] = {"reward_graph": {
        "threshold": report.reward_threshold,
        "scores": dict(zip(causes, significant(report.reward_scores, 4))),  # as the dynamics graph's cmi
        "learned_parents": [c for c, p in zip(causes, report.reward_parents) if p],
        "true_parents": (None if report.true_reward_parents is None
                         else [c for c, p in zip(causes, report.true_reward_parents) if p]),
        **{k: float(m[f"reward_{k}"]) for k in REWARD_SCORES if f"reward_{k}" in m}}}
    if report.reward_stderr is not None:  # CBM's reward CMI: delta-method standard errors (issue 22)
        out["reward_graph"]["stderr"] = dict(zip(causes, significant(report.reward_stderr, 3)))
        out["reward_graph"]["undecided"] = [c for c, u in zip(causes, report.reward_undecided) if u]
        if report.reward_min_cmi > 0.0:
            out["reward_graph"]["min_cmi"] = report.reward_min_cmi  # the fdr rule's effect size for this row
    out["task_abstraction"] = task_abstraction_fields(report)
    if any(is_distractor(n) for n in names) and report.true_graph is not None:
        out["distractors"] = distractor_scores(report.adjacency, report.true_graph, report.factor_names)
    return out


def task_abstraction_fields(report: GraphReport) -> dict[str, Any]:
    """Fig. 4.2 (b)'s split of the learned minimal abstraction, the true one, and CDL's beside them."""
    names = report.factor_names
    d = len(names)
    kept = set(report.controllable + report.action_relevant)
    parents = {j for j in range(d) if report.reward_parents[j]}
    out: dict[str, Any] = {
        "kept": [names[j] for j in sorted(kept)], "reward_parents": [names[j] for j in sorted(parents & kept)],
        "ancestors": [names[j] for j in sorted(kept - parents)],
        "dropped": [names[j] for j in range(d) if j not in kept],
        "cdl_kept": [names[j] for j in cdl_abstraction(report.adjacency).kept]}
    if report.true_graph is not None and report.true_reward_parents is not None:
        truth = minimal_abstraction(report.true_graph, report.true_reward_parents).kept
        out["true_kept"] = [names[j] for j in truth]
        for key in ("abstraction_accuracy", "abstraction_accuracy_true_reward"):
            if key in report.metrics:
                out[key.replace("abstraction_", "")] = float(report.metrics[key])
    return out


def distractor_scores(adjacency: np.ndarray, truth: np.ndarray, names: tuple[str, ...]) -> dict[str, Any]:
    """Table 4.1's accuracy is dominated by true negatives: beside it, what an empty graph scores and F1
    over the entries whose cause and effect (the action counts as a cause) are no distractors."""
    plain = np.array([not is_distractor(n) for n in names])
    scored = scored_entries(truth.shape)
    inner = scored & plain[:, None] & np.append(plain, True)[None, :]
    learned, true = adjacency.astype(bool), truth.astype(bool)
    every = np.ones(truth.shape, dtype=bool)
    return {"count": int((~plain).sum()),
            "accuracy": binary_scores(learned, true, scored)["accuracy"],
            "with_self_accuracy": binary_scores(learned, true, every)["accuracy"],
            "empty_graph_accuracy": float(1 - true[scored].mean()),
            "empty_graph_with_self_accuracy": float(1 - true.mean()),
            "non_distractor_f1": binary_scores(learned, true, inner)["f1"],
            "non_distractor_accuracy": binary_scores(learned, true, inner)["accuracy"],
            "distractor_errors": int(((learned != true) & scored & ~inner).sum())}


def plot_abstraction(report: GraphReport, path: Path, label: str = "last report") -> None:
    """Figs. 4.5-4.6 for one run: which factors each abstraction keeps (the learned minimal one, the true
    one, CDL's of the same graph), the reward's parents marked."""
    fields = task_abstraction_fields(report)
    names = list(report.factor_names)
    rows = [("CBM (learned)", fields["kept"]), ("CDL's abstraction of the graph", fields["cdl_kept"])]
    if "true_kept" in fields:
        rows.insert(0, ("true minimal", fields["true_kept"]))
    grid = np.array([[1.0 if n in kept else 0.0 for n in names] for _, kept in rows])
    learned = [title for title, _ in rows].index("CBM (learned)")
    grid[learned, [names.index(n) for n in fields["reward_parents"]]] = 1.6
    fig, ax = plt.subplots(figsize=(max(7.0, 0.24 * len(names)), 0.55 * len(rows) + 1.8))
    ax.imshow(grid, cmap="Greens", vmin=-0.3, vmax=1.8, aspect="auto")
    ax.set_yticks(range(len(rows)), [r[0] for r in rows], fontsize=8)
    ax.set_xticks(range(len(names)), names, rotation=90, fontsize=7)
    accuracy = fields.get("accuracy")
    ax.set_title(f"{report.kind} {label}: factors kept (dark; darkest: the reward's learned parents)"
                 + (f", abstraction accuracy {accuracy:.3f}" if accuracy is not None else ""), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
