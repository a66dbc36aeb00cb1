"""benchmarks.fdr_graphs (issue 22): the goal check, reading earlier runs once each, the table, and a
tiny run end to end (3 objects, 20 updates: the figures are meaningless, their relations are not)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import fdr_graphs


def run_row(graph: str, seed: int, fixed: float, tested: float, oracle: float, updates: int = 2_000,
            split: float = 0.5, mirror: float = 0.5, mirror_permuted: float = 0.5) -> dict:
    """A run's row as the benchmark writes it, with only the keys the tables read."""
    def f1(value: float) -> dict:
        return {"f1": value, "fdr": 0.0}

    recall = {str(n): 0.5 for n in fdr_graphs.HELDOUT_SIZES}
    return {"graph": graph, "seed": seed, "updates": updates, "true_edges": 9, "weak_true_edges": 1,
            "fixed": f1(fixed), "fdr_graph": f1(tested), "fdr_permuted": f1(0.5), "fdr_pooled": f1(0.5),
            "fdr_global": f1(0.5), "fdr_split": f1(split), "fdr_mirror": f1(mirror),
            "fdr_mirror_permuted": f1(mirror_permuted), "oracle_f1": oracle,
            "split_level": 2e-3, "mirror_level": None, "mirror_permuted_levels": [1e-3, 2.5],
            "largest_non_edge_cmi": 1e-3, "best_level_f1": oracle,
            **{f"weak_recall_by_heldout{s}": recall for s in fdr_graphs.SUFFIXES}}


@pytest.mark.parametrize(("fixed", "tested", "oracle", "met"), [
    (0.900, 1.000, 1.000, True),
    (0.778, 0.842, 0.872, True),     # 0.030 below the oracle: within the margin
    (0.778, 0.841, 0.872, False),    # 0.031 below
    (0.950, 0.940, 0.950, False),    # within the margin, but below the fixed threshold
    (0.8421052, 0.8421052, 0.8717949, True),  # random10 seed 0's figures, unrounded
])
def test_the_goal_is_within_the_margin_of_the_oracle_and_not_below_the_fixed_graph(fixed, tested, oracle, met) -> None:
    assert fdr_graphs.goal_met(run_row("g", 0, fixed, tested, oracle)) is met


def test_a_run_given_twice_counts_once_and_logs_read_like_json(tmp_path: Path) -> None:
    first = [run_row("chain", 0, 1.0, 1.0, 1.0), run_row("full", 0, 0.9, 1.0, 1.0)]
    (tmp_path / "fdr.json").write_text(json.dumps(first))
    rerun = run_row("full", 0, 0.9, 0.95, 1.0)
    (tmp_path / "more.log").write_text("training...\n" + json.dumps(rerun) + "\n"
                                       + json.dumps(run_row("full", 1, 0.9, 1.0, 1.0)) + "\n| a table |\n")
    rows = fdr_graphs.read_rows([tmp_path / "fdr.json", tmp_path / "more.log"])
    assert sorted((r["graph"], r["seed"]) for r in rows) == [("chain", 0), ("full", 0), ("full", 1)]
    assert next(r for r in rows if (r["graph"], r["seed"]) == ("full", 0))["fdr_graph"]["f1"] == 0.95
    other_budget = run_row("full", 0, 0.9, 0.8, 1.0, updates=500)
    (tmp_path / "short.log").write_text(json.dumps(other_budget) + "\n")
    assert len(fdr_graphs.read_rows([tmp_path / "fdr.json", tmp_path / "short.log"])) == 3


def test_the_table_gives_mean_and_sd_over_seeds_and_counts_the_runs_meeting_the_goal() -> None:
    rows = [run_row("full", 0, 0.900, 1.000, 1.000, split=1.0), run_row("full", 1, 0.900, 0.900, 1.000, split=1.0),
            run_row("full", 2, 0.952, 1.000, 1.000, split=0.9, mirror=1.0, mirror_permuted=1.0),
            run_row("chain", 0, 1.0, 1.0, 1.0, mirror_permuted=1.0)]
    lines = fdr_graphs.table(rows, 0.05, 5e-3).splitlines()
    assert "goal met" in lines[0] and lines[0].count("|") == lines[1].count("|") == lines[2].count("|")
    full = lines[2].split(" | ")
    assert full[0] == "| full" and full[1] == "3"
    assert full[4] == f"{np.mean([1.0, 0.9, 1.0]):.3f} ± {np.std([1.0, 0.9, 1.0], ddof=1):.3f}"
    assert lines[2].endswith("| 2 of 3 | 2 of 3 | 1 of 3 | 1 of 3 |")
    assert lines[3].endswith("| 1 of 1 | 0 of 1 | 0 of 1 | 1 of 1 |")
    per_run = fdr_graphs.split_table(rows).splitlines()
    assert per_run[0].count("|") == per_run[1].count("|") == per_run[2].count("|") == 17
    assert per_run[2].startswith("| chain | 0 |") and per_run[2].endswith("| yes / no / no / yes |")
    assert "| 2.00e-03 | none (min_cmi) | 1.00e-03 / 2.50 |" in per_run[2]


@pytest.mark.timeout(180)
def test_a_tiny_run_writes_rows_whose_graphs_agree_with_each_other(tmp_path: Path, capsys) -> None:
    fdr_graphs.main(["--graphs", "chain", "--objects", "3", "--seeds", "0", "--updates", "20", "--train", "2000",
                     "--out", str(tmp_path)])
    (row,) = json.loads((tmp_path / "fdr.json").read_text())
    assert (row["graph"], row["seed"], row["updates"]) == ("chain", 0, 20)
    assert row["by_min_cmi"][str(5e-3)] == row["fdr_graph"]
    assert row["oracle_f1"] >= row["fixed"]["f1"] - 1e-9  # the best threshold is at least the 0.02 one
    est = {k: np.array(v) for k, v in row["estimate"].items()}
    assert est["cmi"].shape == (9, 10) and (est["stderr"] >= 0).all()
    truth = np.array(row["truth"], bool)
    assert row["true_edges"] == int((truth & ~np.eye(9, 10, dtype=bool)).sum())
    recall = [row["weak_recall_by_heldout"][str(n)] for n in fdr_graphs.HELDOUT_SIZES]
    assert all(0.0 <= r <= 1.0 for r in recall)
    assert row["split_level"] is None or 0.0 < row["split_level"] <= 0.02
    assert row["mirror_level"] is None or 0.0 < row["mirror_level"] <= 0.02
    assert row["mirror_permuted_levels"] is None or (0.0 < row["mirror_permuted_levels"][0] <= 0.02
                                                     and row["mirror_permuted_levels"][1] > 0.0)
    assert row["largest_non_edge_cmi"] == pytest.approx(float(est["cmi"][~truth & ~np.eye(9, 10, dtype=bool)].max()), rel=1e-5)
    old = {k: v for k, v in row.items()
           if k not in ("fdr_split", "split_level", "fdr_mirror", "mirror_level", "fdr_mirror_permuted",
                        "mirror_permuted_levels", "largest_non_edge_cmi")}
    again = fdr_graphs.with_levels(old, 0.05, 5e-3)    # a row from before the split and mirror rules, filled from its estimate
    assert set(again["fdr_split"]) == set(row["fdr_split"]) and 0.0 <= again["fdr_split"]["f1"] <= 1.0
    assert again["fdr_mirror"]["f1"] == pytest.approx(row["fdr_mirror"]["f1"])   # the dump keeps 6 digits
    assert (again["mirror_level"] is None) == (row["mirror_level"] is None)
    assert again["mirror_level"] is None or again["mirror_level"] == pytest.approx(row["mirror_level"], rel=1e-5)
    assert "weak_recall_by_heldout_mirror" not in again and "weak_recall_by_heldout_mirror" in row
    assert again["fdr_mirror_permuted"]["f1"] == pytest.approx(row["fdr_mirror_permuted"]["f1"])
    assert (again["mirror_permuted_levels"] is None) == (row["mirror_permuted_levels"] is None)
    assert again["best_level_f1"] >= max(v["f1"] for k, v in row["by_min_cmi"].items() if float(k) >= 1e-4) - 1e-9
    assert "| chain | 1 |" in capsys.readouterr().out


def test_runs_of_one_graph_at_several_budgets_get_a_row_each() -> None:
    rows = [run_row("random10", 1, 0.84, 0.87, 0.90, updates=4_000), run_row("random10", 1, 0.74, 0.81, 0.82, updates=1_200),
            run_row("chain", 0, 1.0, 1.0, 1.0)]
    lines = fdr_graphs.table(rows, 0.05, 5e-3).splitlines()
    assert [line.split(" | ")[0] for line in lines[2:]] == ["| random10, 4000 updates", "| random10, 1200 updates", "| chain"]
    assert lines[2].split(" | ")[3] == "0.840 ± 0.000"
