"""What a run leaves behind about local graphs: the summary's ``local_graph`` section, a picture of
example transitions' estimated local graphs beside their truth, and the local scores over the run."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from causal.graph_metrics import scored_entries  # noqa: E402
from proto.messages import LocalGraphReport  # noqa: E402
from services.supervisor.report import comparison_heatmap, plot_scores  # noqa: E402

CURVE_KEYS = ("roc_auc", "pr_auc", "best_f1", "f1")


def local_fields(report: LocalGraphReport) -> dict[str, Any]:
    """A local-graph report's scores and facts, for a summary."""
    return {"estimator": report.estimator, "threshold": report.threshold, "num_transitions": report.num_transitions,
            "weights_version": report.weights_version, "graph_env_steps": report.env_steps,
            "graph_updates": report.updates, "scoring": "pooled over every off-diagonal entry of every transition",
            **{k: float(v) for k, v in report.metrics.items()}}


def score_line(report: LocalGraphReport) -> str:
    m = report.metrics
    return (f"{report.estimator} ROC AUC {m['roc_auc']:.3f}, PR AUC {m['pr_auc']:.3f}, best F1 {m['best_f1']:.3f} "
            f"(true edges {100 * m['positive_rate']:.1f}% of entries)")


def plot_examples(report: LocalGraphReport, path: Path, label: str = "last report") -> None:
    """One column per example transition: estimated local graph at the report's threshold vs truth."""
    k = report.scores.shape[0]
    if k == 0:
        return
    names = list(report.factor_names) + ["action"]
    side = max(5.0, 0.26 * len(names))
    fig, axes = plt.subplots(1, k, figsize=(side * k, side), squeeze=False)
    self_edges = ~scored_entries(report.truth.shape[1:])  # kept by assumption: shown as found, not scored
    for i, ax in enumerate(axes[0]):
        comparison_heatmap(ax, (report.scores[i] >= report.threshold) | self_edges, report.truth[i] | self_edges,
                           f"transition {i + 1}", names, report.factor_names)
    m = report.metrics
    fig.suptitle(f"{report.kind} local graphs ({report.estimator} >= {report.threshold:g}), {label}, weights "
                 f"v{report.weights_version}: ROC AUC {m['roc_auc']:.3f}, PR AUC {m['pr_auc']:.3f}, "
                 f"best F1 {m['best_f1']:.3f} over {report.num_transitions} transitions")
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_curve(history: list[dict[str, float]], path: Path) -> None:
    """Local-graph scores against env steps over the run."""
    plot_scores(history, CURVE_KEYS, "local-graph score", path)
