"""What a run leaves behind: summary.json, the learned graph beside the true one, learning curves."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from causal.abstraction import Abstraction  # noqa: E402
from causal.graph_metrics import binary_scores, scored_entries  # noqa: E402
from proto.messages import GraphReport  # noqa: E402
from services.supervisor.report_reward import reward_fields  # noqa: E402
from services.supervisor.rounding import significant  # noqa: E402

SUMMARY_SCORES = ("accuracy", "precision", "recall", "f1", "roc_auc", "best_threshold", "best_threshold_f1",
                  "best_threshold_accuracy", "best_threshold_precision", "best_threshold_recall")
IDENTIFIABLE_SCORES = tuple(f"identifiable_{k}" for k in SUMMARY_SCORES) + ("unidentifiable_true_edges",)
"""The same scores without the columns of factors that are constant by construction (see
:func:`causal.graph_metrics.score_graph`); equal to the others in environments without such factors."""
WITH_SELF_SCORES = tuple(f"with_self_{k}" for k in SUMMARY_SCORES)
"""The same scores over every entry, self-edges included and kept: Table 3.1's scoring (see
:mod:`causal.graph_metrics`)."""


def summary(report: GraphReport | None, base: dict[str, Any], history: list[dict[str, float]]) -> dict[str, Any]:
    """summary.json content: the run's facts plus the last graph report's scores and matrices, as the
    ``graph`` block of the results contract (docs/scoring.md) and, as before the contract, at the top
    level too (tools written against the older layout read them there)."""
    out = dict(base)
    if report is None:
        out["graph_report"] = None
        return out
    fields = graph_fields(report)
    out["graph"] = {"evaluation": "last live report", **fields}
    out.update(fields)
    out["scoring"] = ("off-diagonal entries of the d_S x (d_S+1) graph (self-edges are assumed, not scored); "
                      "identifiable_*: also without the columns of factors constant by construction; "
                      "with_self_*: every entry, self-edges included and kept (Table 3.1's scoring)")
    out["history"] = history
    return out


def graph_fields(report: GraphReport) -> dict[str, Any]:
    """A graph report's scores, matrices, abstraction and object-level scores, for a summary."""
    abstraction = Abstraction(report.controllable, report.action_relevant, report.action_irrelevant)
    out: dict[str, Any] = {k: float(report.metrics[k]) for k in SUMMARY_SCORES + IDENTIFIABLE_SCORES + WITH_SELF_SCORES
                           if k in report.metrics}
    out.update({
        "threshold": report.threshold,
        "weights_version": report.weights_version,
        "graph_env_steps": report.env_steps,
        "graph_updates": report.updates,
        "num_heldout": report.num_heldout,
        "factor_names": list(report.factor_names) + ["action"],
        "learned_graph": report.adjacency.astype(int).tolist(),
        "true_graph": report.true_graph.astype(int).tolist() if report.true_graph is not None else None,
        "cmi": significant(report.cmi, 4),  # not decimals: the fdr rule's level can sit at 1e-4 nats and
        # --evaluator-bias mirror's is read from entries far smaller
        "abstraction": abstraction.named(report.factor_names),
        **edge_test_fields(report),
    })
    objects = object_scores(report.adjacency, report.true_graph, report.factor_names)
    if objects is not None:
        out["object_level"] = objects
    out.update(reward_fields(report))  # a method with a reward graph (CBM): reward_graph, task_abstraction, ...
    return out


def edge_test_fields(report: GraphReport) -> dict[str, Any]:
    """How the report decided its edges (``edge_rule``, and ``fdr`` / ``min_cmi`` under the fdr rule)
    and, where the estimator has them, each entry's standard error and which entries are undecided."""
    out: dict[str, Any] = {"edge_rule": report.edge_rule}
    if report.edge_rule == "fdr":
        out.update(fdr=report.fdr, min_cmi=report.min_cmi, bias=report.bias)
    if report.cmi_null is not None:
        out["cmi_null"] = significant(report.cmi_null, 3)
    if report.cmi_stderr is not None:
        out["cmi_stderr"] = significant(report.cmi_stderr, 3)
        out["undecided"] = report.undecided.astype(int).tolist()
        out["undecided_entries"] = int(report.undecided.sum())
    return out


def score_line(metrics: dict[str, float]) -> str:
    """One line of a report's headline scores (Table 3.1's beside ours, where present)."""
    if "f1" not in metrics:
        return "no ground truth to score against"
    shown = (("f1", "F1"), ("accuracy", "accuracy"), ("best_threshold_f1", "best-threshold F1"),
             ("with_self_best_threshold_f1", "Table 3.1 scoring: F1"), ("with_self_best_threshold_accuracy", "accuracy"))
    return ", ".join(f"{label} {metrics[key]:.3f}" for key, label in shown if key in metrics)


def object_scores(adjacency: np.ndarray, truth: np.ndarray | None, names: tuple[str, ...]) -> dict[str, Any] | None:
    """Accuracy, precision, recall and F1 of the object-level graph (Figure 3.5, right), scored like
    the factor graph: every entry but an object's dependence on itself; the edges it misses and adds.
    None without a true graph or without multi-dimensional objects (Chemical: the factor graph)."""
    if truth is None or all("." not in n for n in names):
        return None
    learned, objects = object_level(adjacency, names)
    true, _ = object_level(truth, names)
    mask = scored_entries(true.shape)
    learned, true = learned.astype(bool), true.astype(bool)
    causes = objects + ["action"]

    def edges(matrix: np.ndarray) -> list[str]:
        return [f"{causes[i]} -> {objects[j]}" for j, i in zip(*np.nonzero(matrix & mask))]

    return {**binary_scores(learned, true, mask), "true_edges": int(np.sum(true & mask)),
            "missed": edges(true & ~learned), "spurious": edges(learned & ~true)}


def write_summary(path: Path, content: dict[str, Any]) -> None:
    path.write_text(json.dumps(content, indent=1) + "\n")


def plot_graphs(report: GraphReport, path: Path, label: str = "last report") -> None:
    """Heat maps: learned CMI graph, true graph, and the comparison (TP / FP / FN marked)."""
    names = list(report.factor_names) + ["action"]
    panels = [("learned: log10 CMI (nats), self-edges blank", _log_cmi(report.cmi, report.threshold), "viridis")]
    if report.true_graph is not None:
        panels.append(("ground truth", report.true_graph.astype(float), "Greys"))
        panels.append(("learned vs truth", _comparison(report.adjacency, report.true_graph), None))
    side = max(6.5, 0.28 * len(names))
    fig, axes = plt.subplots(1, len(panels), figsize=(side * len(panels), side), squeeze=False)
    for ax, (title, matrix, cmap) in zip(axes[0], panels):
        _heatmap(ax, matrix, cmap, title, names, report.factor_names)
    f1 = report.metrics.get("f1")
    fig.suptitle(f"{report.kind} {label}, weights v{report.weights_version}, {report.env_steps} env steps, "
                 f"CMI on {report.num_heldout} held-out transitions" + (f", F1 {f1:.3f}" if f1 is not None else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _log_cmi(cmi: np.ndarray, threshold: float) -> np.ndarray:
    """log10 of CMI floored at threshold / 100, with the (always kept) self-edges masked out."""
    out = np.log10(np.clip(cmi.astype(float), threshold / 100, None))
    n = cmi.shape[0]
    out[np.arange(n), np.arange(n)] = np.nan
    return out


def _comparison(learned: np.ndarray, truth: np.ndarray) -> np.ndarray:
    learned, truth = learned.astype(bool), truth.astype(bool)
    code = np.zeros(learned.shape)
    code[learned & truth] = 3     # true positive
    code[learned & ~truth] = 2    # false positive
    code[~learned & truth] = 1    # false negative
    return code


def comparison_heatmap(ax, learned: np.ndarray, truth: np.ndarray, title: str, cols: list[str],
                       rows: tuple[str, ...]) -> None:
    """A learned 0/1 graph against the truth on ``ax``: TP green, FP red, FN orange."""
    _heatmap(ax, _comparison(learned, truth), None, title, cols, rows)


def _heatmap(ax, matrix: np.ndarray, cmap: str | None, title: str, cols: list[str], rows: tuple[str, ...]) -> None:
    if cmap is None:
        from matplotlib.colors import ListedColormap
        cmap = ListedColormap(["#f4f4f4", "#e0a030", "#d03030", "#2a8a3a"])
        ax.imshow(matrix, cmap=cmap, vmin=0, vmax=3)
        ax.set_title(title + "\n(green TP, red FP, orange FN)")
    else:
        im = ax.imshow(matrix, cmap=cmap, interpolation="nearest")
        ax.set_title(title)
        plt.colorbar(im, ax=ax, fraction=0.046)
    size = 8 if len(cols) <= 20 else 6
    ax.set_xticks(range(len(cols)), cols, rotation=90, fontsize=size)
    ax.set_yticks(range(len(rows)), rows, fontsize=size)
    ax.set_xlabel("cause (factor at t, action last)")
    ax.set_ylabel("effect (factor at t+1)")


def object_level(adjacency: np.ndarray, names: tuple[str, ...]) -> tuple[np.ndarray, list[str]]:
    """Collapse a factor graph to objects (the name before the first '.'): an object edge exists when
    any factor of one object depends on any factor of the other (Figure 3.5, right). The action is
    kept as the last column."""
    objects = list(dict.fromkeys(n.split(".", 1)[0] for n in names))
    group = np.array([objects.index(n.split(".", 1)[0]) for n in names])
    out = np.zeros((len(objects), len(objects) + 1), dtype=np.uint8)
    for j, i in zip(*np.nonzero(adjacency)):
        col = len(objects) if i == len(names) else group[i]
        out[group[j], col] = 1
    return out, objects


def plot_object_graphs(report: GraphReport, path: Path) -> None:
    """Learned and true object-level graphs side by side (self-dependencies of objects are shown)."""
    learned, objects = object_level(report.adjacency, report.factor_names)
    panels = [("learned (object level)", learned)]
    if report.true_graph is not None:
        panels.append(("ground truth (object level)", object_level(report.true_graph, report.factor_names)[0]))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 4.2), squeeze=False)
    for ax, (title, matrix) in zip(axes[0], panels):
        ax.imshow(matrix, cmap="Greys", vmin=0, vmax=1.4, interpolation="nearest")
        ax.set_xticks(range(len(objects) + 1), objects + ["action"], rotation=90)
        ax.set_yticks(range(len(objects)), objects)
        ax.set_title(title)
        ax.set_xlabel("cause (t)")
        ax.set_ylabel("effect (t+1)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_learning_curve(history: list[dict[str, float]], path: Path) -> None:
    """Graph scores against env steps over the run."""
    if not history:
        return
    keys = ["f1", "best_threshold_f1", "accuracy", "roc_auc"]
    if history[0].get("unidentifiable_true_edges", 0) > 0:  # else identical to the full scores
        keys += ["identifiable_f1", "identifiable_best_threshold_f1"]
    keys += ["with_self_best_threshold_f1"]  # the figure Table 3.1 reports
    plot_scores(history, keys, "score", path)


def plot_live_scores(history: list[dict[str, float]], path: Path) -> None:
    """The learner's live scores against its updates: the scores in [0, 1] (DCI, FG-ARI) on the left,
    the others (PSNR in dB, KL in nats) on the right."""
    if not history:
        return
    keys = [k for k in history[-1] if k not in ("time", "updates", "env_steps")]
    unit = [k for k in keys if all(0.0 <= h.get(k, 0.0) <= 1.0 for h in history)]
    panels = [(unit, "score"), ([k for k in keys if k not in unit], "dB / nats")]
    panels = [(ks, label) for ks, label in panels if ks]
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4), squeeze=False)
    updates = [h["updates"] for h in history]
    for ax, (ks, label) in zip(axes[0], panels):
        for key in ks:
            ax.plot(updates, [h.get(key, float("nan")) for h in history], label=key)
        ax.set_xlabel("learner updates")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    fig.suptitle("live scores of the learner on fixed unseen data")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_scores(history: list[dict[str, float]], keys: list[str] | tuple[str, ...], ylabel: str, path: Path) -> None:
    """Scores in [0, 1] against env steps, one line per key the history has."""
    if not history:
        return
    steps = [h["env_steps"] for h in history]
    fig, ax = plt.subplots(figsize=(7, 4))
    for key in keys:
        if key in history[0]:  # a report without the key (forged, or of an older evaluator) leaves a gap
            ax.plot(steps, [h.get(key, float("nan")) for h in history], label=key)
    ax.set_xlabel("env steps")
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def policy_summary(stats: dict[tuple[str, str], dict[str, float]],
                   timeline: list[tuple[float, str, str, float]]) -> dict[str, Any]:
    """The weight broadcast at the end of a run with a policy: the last published version, the
    version each env-worker acted with, the policy-lag distribution of the batches the
    policy-learner received and its drops by reason (from the services' last stats beats); for a
    policy over skills also the skills started, summed over workers, by the Uniform warm-up policy
    and by the learned one, the decisions the learner stitched and their mean return per option."""
    learner = next((v for (service, _), v in stats.items() if service == "policy-learner"), {})
    options: dict[str, dict[str, int]] = {}
    for (service, _), values in sorted(stats.items()):
        for key, n in values.items():
            if service == "env-worker" and key.startswith("options_"):
                policy, option = key[len("options_"):].split("_", 1)
                started = options.setdefault(policy, {})
                started[option] = started.get(option, 0) + int(n)
    returns = {key[len("return_"):]: round(v, 4) for key, v in learner.items() if key.startswith("return_")}
    extra = {"skill_options": options, "decisions": int(learner.get("decisions", 0)),
             "decisions_discarded": int(learner.get("decisions_discarded", 0)),
             "mean_return_by_option": returns} if options else {}
    lags = {key[4:]: int(v) for key, v in learner.items() if key.startswith("lag_")}
    order = sorted((k for k in lags if k.isdigit()), key=int) + [k for k in ("over", "future") if k in lags]
    return {
        "published_version": int(learner.get("policy_version", 0)),
        "worker_versions": {inst: int(v.get("policy_version", 0)) for (service, inst), v in sorted(stats.items())
                            if service == "env-worker"},
        "lag_histogram": {k: lags[k] for k in order},
        "dropped": {key[8:]: int(v) for key, v in learner.items() if key.startswith("dropped_")},
        "version_timeline": [[round(t, 2), f"{service}/{inst}", int(v)] for t, service, inst, v in timeline],
        **extra,
    }


def plot_policy(policy: dict[str, Any], path: Path) -> None:
    """Left: published policy version and each worker's version in use over the run. Right: the
    policy-lag distribution of received batches (versions behind the learner when they arrived)."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 3.8))
    series: dict[str, list[tuple[float, int]]] = {}
    for t, who, version in policy["version_timeline"]:
        series.setdefault(who, []).append((t, version))
    for who, points in sorted(series.items()):
        t, v = zip(*points)
        label = "published (policy-learner)" if who.startswith("policy-learner") else f"in use: {who}"
        left.step(t, v, where="post", label=label, linewidth=2.5 if "learner" in who else 1.2)
    left.set_xlabel("seconds since start")
    left.set_ylabel("policy version")
    left.set_title("weight broadcast")
    left.grid(alpha=0.3)
    left.legend(fontsize=7, loc="upper left")
    lags = policy["lag_histogram"]
    total = max(sum(lags.values()), 1)
    right.bar(list(lags), [n / total for n in lags.values()], color="#4a7ab0")
    right.set_xlabel("policy lag of a received batch (versions)")
    right.set_ylabel("fraction of batches")
    dropped = ", ".join(f"{k} {v}" for k, v in policy["dropped"].items() if v) or "none"
    right.set_title(f"lag distribution ({total} batches; dropped: {dropped})", fontsize=9)
    right.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
