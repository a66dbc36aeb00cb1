"""CDL over slots from pixels beside CDL over the state, at the object level (issue 24, item 5).

A run with ``--env chemical-pixels --worker-publish-frames true`` learns its graph over the
factor-extractor's slots, put in object order by the identity head: one factor per object (and the
background). A state-based run of the same env learns a graph over every object's colour and
position. Both are scored here on the same object graph: the state run's CMI collapsed to objects
(an object pair's score is the largest CMI between any of their factors, the action kept as the last
column), the slot run's CMI without its background row and column; off-diagonal entries, as every
graph is scored (:func:`causal.graph_metrics.score_graph`). Each run's last live report is used (the
slot run has no final graph: its final model's factors are the extractor's); the state run's final
graph is added where it has one.

    python -m benchmarks.pixels_vs_state --pixels runs/pixels-full4 --state runs/state-full4 [--out FILE]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from causal.graph_metrics import score_graph
from services.supervisor.report import object_level

SHOWN = ("f1", "best_threshold_f1", "roc_auc", "precision", "recall")


def collapse(cmi: np.ndarray, names: list[str]) -> tuple[np.ndarray, list[str]]:
    """A factor-level score matrix ``[d, d + 1]`` (names of the d factors then ``action``) to objects
    ``[N, N + 1]``: the largest score between any factor of one object and any of the other."""
    factors = names[:-1]
    objects = list(dict.fromkeys(n.split(".", 1)[0] for n in factors))
    group = np.array([objects.index(n.split(".", 1)[0]) for n in factors] + [len(objects)])
    out = np.full((len(objects), len(objects) + 1), -np.inf)
    for j, i in np.ndindex(cmi.shape):
        out[group[j], group[i]] = max(out[group[j], group[i]], cmi[j, i])
    return out, objects


def object_scores(graph: dict[str, Any], threshold: float) -> dict[str, Any]:
    """A summary's graph block scored at the object level (background dropped where there is one)."""
    names, cmi = list(graph["factor_names"]), np.asarray(graph["cmi"], dtype=float)
    truth = np.asarray(graph["true_graph"], dtype=np.uint8)
    if names[0] == "background":
        cmi, truth, names = cmi[1:, 1:], truth[1:, 1:], names[1:]
        objects = names[:-1]
    else:
        cmi, objects = collapse(cmi, names)
        truth = object_level(truth, tuple(names[:-1]))[0]
    scores = score_graph(cmi, truth, threshold)
    return {"objects": objects, "true_edges": int(truth.sum() - np.trace(truth[:, :-1])),
            **{k: float(scores[k]) for k in SHOWN}}


def compare(pixels: dict[str, Any], state: dict[str, Any]) -> dict[str, Any]:
    rows = {"pixels (slots), last report": object_scores(pixels, pixels["threshold"]),
            "state, last report": object_scores(state, state["threshold"])}
    if "final_graph" in state:
        rows["state, final graph"] = object_scores(state["final_graph"], state["final_graph"]["threshold"])
    budget = {name: {k: run.get(k) for k in ("env_steps", "updates", "wall_seconds", "graph_updates")}
              for name, run in (("pixels", pixels), ("state", state))}
    return {"rows": rows, "slots": pixels.get("slots", {}), "budget": budget}


def table(result: dict[str, Any]) -> str:
    lines = ["| run | " + " | ".join(SHOWN) + " |", "|---" * (len(SHOWN) + 1) + "|"]
    for name, row in result["rows"].items():
        lines.append(f"| {name} | " + " | ".join(f"{row[k]:.3f}" for k in SHOWN) + " |")
    slots = result["slots"]
    lines.append("")
    lines.append("slots: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                                       for k, v in slots.items() if k != "evaluation"))
    for name, budget in result["budget"].items():
        lines.append(f"{name}: " + ", ".join(f"{k} {v}" for k, v in budget.items()))
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pixels", type=Path, required=True, help="run directory of the slot (pixel) run")
    parser.add_argument("--state", type=Path, required=True, help="run directory of the state-based run")
    parser.add_argument("--out", type=Path, default=None, help="write the comparison as JSON")
    args = parser.parse_args()
    runs = [json.loads((d / "summary.json").read_text()) for d in (args.pixels, args.state)]
    for d, run in zip((args.pixels, args.state), runs):
        if run.get("true_graph") is None or run.get("cmi") is None:
            parser.error(f"{d}: its summary has no scored graph report (no true graph, or no report)")
    result = compare(*runs)
    print(table(result))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
