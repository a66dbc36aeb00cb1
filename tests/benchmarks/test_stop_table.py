"""The stop-rule table reads each run's summary: which runs the stable-graph rule stopped, and at what F1."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.stop_table import by_graph, main, row


def _summary(run: Path, stopped_because: str, f1: float, oracle: float, **extra: object) -> Path:
    run.mkdir(parents=True)
    summary = {"env": "chemical", "env_options": {"graph": "envs/dags/random5-6-1.json", "num_objects": 5},
               "seed": 1, "edge_rule": "fdr", "fdr": 0.05, "bias": "fixed", "min_cmi": 0.005,
               "stopped_because": stopped_because, "wall_seconds": 151.3, "updates": 10_580, "num_heldout": 16_000,
               "undecided_entries": 0, "f1": f1, "precision": 1.0, "recall": f1, "best_threshold_f1": oracle,
               # a weak true edge (0 <- 1) at 0.01 nats, below the fixed 0.02; the other true edge strong
               "true_graph": [[1, 1, 0, 0], [0, 1, 1, 0], [0, 0, 1, 0]],
               "cmi": [[0.5, 0.01, 0.001, 0.0], [0.0, 0.5, 0.3, 0.001], [0.002, 0.0, 0.5, 0.0]], **extra}
    (run / "summary.json").write_text(json.dumps(summary))
    return run


def test_rows_tell_the_rule_from_a_budget_and_the_oracle(tmp_path, capsys) -> None:
    stable = _summary(tmp_path / "a", "graph stable: unchanged for 10 reports (45s), no undecided entry (fdr rule)",
                      1.0, 1.0)
    budget = _summary(tmp_path / "b", "time budget 420s reached", 0.9, 0.952, undecided_entries=2, bias="split")
    first, second = row(stable), row(budget)
    assert first["stopped"] and not second["stopped"]
    assert first["graph"] == "random5-6-1, 5 objects" and first["rule"] == "fdr (0.05, 0.005)"
    assert second["rule"] == "fdr (0.05, split)" and second["undecided"] == 2
    assert first["fixed_f1"] == pytest.approx(2 / 3)  # at 0.02: one of the two true edges, no false one
    (budget / "config.json").write_text(json.dumps({"evaluator": {"eval_samples": 2000, "eval_samples_max": 0}}))
    assert row(budget)["rule"] == "fdr (0.05, split), draw fixed at 2,000"
    (same_rule,) = by_graph([first, row(_summary(tmp_path / "c", "time budget 420s reached", 0.9, 0.952))])
    assert same_rule["runs"] == 2 and same_rule["stopped"] == 1 and same_rule["at_oracle"] == 1
    assert same_rule["f1"] == pytest.approx(0.95)
    main([str(stable), str(budget), "--out", str(tmp_path / "out.json")])
    printed = capsys.readouterr().out
    assert "151 s: stable graph" in printed and "budget (time budget 420s reached)" in printed
    assert len(json.loads((tmp_path / "out.json").read_text())["runs"]) == 2


def test_a_run_without_a_summary_is_refused(tmp_path) -> None:
    with pytest.raises(SystemExit):
        main([str(tmp_path)])
