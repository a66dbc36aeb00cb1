"""Why ELDEN's pooled local-graph scores differ from its per-entry ones: a breakdown of a trained
run's Jacobian local graphs (eq. 5.1) on Table 5.1's scripted episodes.

For the run's final model and the 50 scripted episodes :mod:`benchmarks.local_graph_table` scores,
this prints: pooled and per-entry scores of three reductions of the raw input Jacobian per input
variable (the reference's, the derivative along the observed category; the sum of absolute
derivatives over every category; the largest derivative of switching to another category) and of
per-(transition, output) normalised scores; F1 / precision / recall at fixed thresholds epsilon with
the share of member entries above each (what Algorithm 6's reward thresholds); the entries with the
most false positives at the best pooled threshold; and the mean score of true edges and non-edges
per output factor.

    python -m benchmarks.elden_graph_breakdown --run runs/local-table-elden/elden-thawing-s0
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from benchmarks.local_graph_table import scripted_transitions
from causal.elden import ELDENModel
from causal.elden_graphs import input_jacobian
from causal.graph_metrics import best_threshold, score_local_graphs, score_local_graphs_per_entry, scored_entries
from services.supervisor.config import load_run_config
from services.supervisor.evaluation import load_model
from services.supervisor.wiring import env_kwargs, run_env_spec

THRESHOLDS = (3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1)


def reductions(model: ELDENModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
               chunk: int = 128) -> dict[str, np.ndarray]:
    """Per-member scores ``[M, B, d_S, d_S + 1]`` of each reduction of the input Jacobian."""
    parts: dict[str, list[torch.Tensor]] = {"observed category (reference)": [], "sum over categories": [],
                                            "switch to another category": []}
    for start in range(0, state.shape[0], chunk):
        s, a, n = (t[start : start + chunk] for t in (state, action, next_state))
        inputs = model.per_member(model.encode(s, a))
        with torch.enable_grad():
            jac = input_jacobian(model, inputs, model.targets(s, n)).detach()
        x = inputs[:, :, None]
        parts["observed category (reference)"].append(model.reduce_inputs(jac, x))
        valid, onehot = model.input_valid, model.input_onehot
        total = (jac.abs() * valid).sum(-1)
        switch = ((jac - (jac * x).sum(-1, keepdim=True)).abs() * valid).amax(-1)
        parts["sum over categories"].append(total)
        parts["switch to another category"].append(torch.where(onehot, switch, total))
    return {name: torch.cat(p, dim=1).numpy() for name, p in parts.items()}


def row_normalised(scores: np.ndarray) -> np.ndarray:
    """Each (transition, output) row of ``[B, d_S, d_S + 1]`` divided by its largest off-diagonal score."""
    off = scored_entries(scores.shape[1:])[None]
    return scores / np.maximum(np.where(off, scores, 0.0).max(-1, keepdims=True), 1e-12)


def report(members: dict[str, np.ndarray], truth: np.ndarray, names: list[str], top: int = 10) -> str:
    lines = ["reduction | pooled ROC AUC / PR AUC / best F1 | per entry ROC AUC / PR AUC / best F1"]
    candidates = {**{k: v.mean(0) for k, v in members.items()},
                  "reference, row-normalised": row_normalised(members["observed category (reference)"].mean(0))}
    for name, scores in candidates.items():
        p, e = score_local_graphs(scores, truth, 0.0), score_local_graphs_per_entry(scores, truth)
        lines.append(f"{name} | {p['roc_auc']:.3f} / {p['pr_auc']:.3f} / {p['best_f1']:.3f} | "
                     f"{e['roc_auc']:.3f} / {e['pr_auc']:.3f} / {e['best_f1']:.3f} ({e['entries']} entries)")
    member = members["observed category (reference)"]
    scores = member.mean(0)
    mask = np.broadcast_to(scored_entries(truth.shape[1:]), truth.shape)
    best, _ = best_threshold(scores, truth, mask=mask)
    lines.append("\nepsilon | F1 / precision / recall | share of member entries >= epsilon")
    for eps in (*THRESHOLDS, best):
        r = score_local_graphs(scores, truth, eps)
        lines.append(f"{eps:.3g} | {r['f1']:.3f} / {r['precision']:.3f} / {r['recall']:.3f} | "
                     f"{(member >= eps)[:, mask].mean():.3f}")
    false = ((scores >= best) & (truth == 0) & mask).sum(0)
    lines.append(f"\nmost false positives at the best pooled threshold {best:.3g} (of {len(truth)} transitions)")
    for k in np.argsort(-false.ravel(), kind="stable")[:top]:
        j, i = np.unravel_index(k, false.shape)
        lines.append(f"{names[i]} -> {names[j]}: {false[j, i]}")
    lines.append("\noutput | mean score of true edges / of non-edges (off-diagonal)")
    for j in range(truth.shape[1]):
        edge, absent = (truth[:, j] == 1) & mask[:, j], (truth[:, j] == 0) & mask[:, j]
        if edge.any():
            lines.append(f"{names[j]} | {scores[:, j][edge].mean():.3g} / {scores[:, j][absent].mean():.3g}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, required=True, help="an ELDEN run directory (its final model)")
    p.add_argument("--episodes", type=int, default=50)
    args = p.parse_args(argv)
    if not (args.run / "summary.json").exists():
        p.error(f"{args.run} is not a finished run (no summary.json)")
    cfg = load_run_config(args.run)
    if cfg.method != "elden":
        p.error(f"{args.run} is a {cfg.method!r} run, not an ELDEN one")
    torch.set_num_threads(1)
    model = load_model(args.run)
    state, action, next_state, truth = scripted_transitions(cfg.env, env_kwargs(cfg), args.episodes)
    members = reductions(model, *(torch.from_numpy(x) for x in (state, action, next_state)))
    names = [*run_env_spec(cfg).factor_names, "action"]
    print(report(members, truth, names))


if __name__ == "__main__":
    main()
