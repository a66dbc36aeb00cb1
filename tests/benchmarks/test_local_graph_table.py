"""Table 5.1's printed table: pooled scores and the per-entry variant beside the chapter's row."""
from __future__ import annotations

from benchmarks.local_graph_table import table


def _result(seed: int, roc: float, per_entry: dict | None) -> dict:
    scored = {"roc_auc": roc, "pr_auc": 0.3, "best_f1": 0.4}
    if per_entry is not None:
        scored["per_entry"] = per_entry
    return {"env": "thawing", "seed": seed, "method": "elden", "estimators": {"jacobian": scored},
            "heldout": {"roc_auc": 0.8, "pr_auc": 0.2, "best_f1": 0.3}}


def test_the_table_shows_pooled_and_per_entry_scores_of_the_results_that_have_them() -> None:
    results = [_result(0, 0.8, {"roc_auc": 0.7, "pr_auc": 0.6, "best_f1": 0.5, "entries": 9}),
               _result(1, 0.9, None)]  # written before per-entry scores existed
    row = next(line for line in table(results, "elden").splitlines() if line.startswith("| thawing | ELDEN"))
    assert row == ("| thawing | ELDEN | 2 | 0.850 ± 0.071 | 0.300 ± 0.000 | 0.400 ± 0.000 | "
                   "0.700 ± 0.000 / 0.600 ± 0.000 / 0.500 ± 0.000 | 0.71 / 0.57 |")
