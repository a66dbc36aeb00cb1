"""benchmarks.rescore_runs: a finished run's summary scored again, with Table 3.1's scoring beside it."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.rescore_runs import main, rescore
from envs.manipulation_truth import global_graph


def _run(tmp_path: Path, name: str, cmi: np.ndarray | None, history: list[dict] | None = None) -> Path:
    run = tmp_path / name
    run.mkdir()
    truth = global_graph()
    summary = {"env": "manipulation", "graph_env_steps": 1234, "threshold": 0.02, "true_graph": truth.tolist(),
               "cmi": None if cmi is None else np.round(cmi, 5).tolist(), "history": history or []}
    (run / "summary.json").write_text(json.dumps(summary))
    return run


def test_a_run_that_finds_every_off_diagonal_edge_but_one_row(tmp_path: Path) -> None:
    truth = global_graph().astype(bool)
    cmi = np.where(truth, 0.3, 0.001)
    cmi[0] = 0.001  # eef.x's 14 off-diagonal true edges missed (its self-edge is kept whatever its CMI)
    row = rescore(_run(tmp_path, "r", cmi))
    assert row["env_steps"] == 1234 and row["precision"] == 1.0
    assert row["recall"] == (112 - 14) / 112 and row["with_self_recall"] == (135 - 14) / 135
    assert row["with_self_accuracy"] == (552 - 14) / 552 and row["with_self_best_threshold_f1"] > row["best_threshold_f1"]


def test_cli_prints_the_table_with_the_chapter_row_and_skips_unscorable_runs(tmp_path: Path, capsys) -> None:
    good = _run(tmp_path, "good", np.where(global_graph() > 0, 0.3, 0.0))
    bad = _run(tmp_path, "bad", None)
    out = tmp_path / "rescore.json"
    assert main([str(good), str(bad), str(tmp_path / "missing"), "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert "| `good` | 1,234 | 1.000 | 1.000 |" in captured.out
    assert "| chapter, Table 3.1 (manipulation) | 1.8M | 0.754 ± 0.008 | 0.902 ± 0.003 |" in captured.out
    assert "bad/summary.json: no graph" in captured.err and "missing/summary.json: cannot read" in captured.err
    assert [r["run"] for r in json.loads(out.read_text())] == ["good"]


def test_mean_row_gives_mean_and_sample_sd_over_seeds(tmp_path: Path, capsys) -> None:
    truth = global_graph().astype(bool)
    runs = []
    for k, missed_rows in enumerate((0, 1, 2)):  # eef.x's, then also eef.y's, 14 off-diagonal edges missed
        cmi = np.where(truth, 0.3, 0.001)
        cmi[:missed_rows] = 0.001
        runs.append(_run(tmp_path, f"s{k}", cmi))
    assert main([*map(str, runs), "--mean", "--out", str(tmp_path / "r.json")]) == 0
    accuracies = [(552 - 14 * m) / 552 for m in (0, 1, 2)]  # each missed row costs its 14 true edges
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| mean ± sd, 3 runs"))
    assert f"| {np.mean(accuracies):.3f} ± {np.std(accuracies, ddof=1):.3f} |" in line
    assert line.startswith("| mean ± sd, 3 runs (manipulation) | 1,234 | ")


def test_window_averages_each_runs_last_reports(tmp_path: Path, capsys) -> None:
    cmi = np.where(global_graph() > 0, 0.3, 0.001)
    history = [{"time": 100.0 * k, "env_steps": 1000 * k, "f1": 0.05 * k, "with_self_best_threshold_f1": 0.1 * k}
               for k in range(11)]  # reports at 0, 100, ..., 1000 s
    older = [{k: v for k, v in h.items() if not k.startswith("with_self_")} for h in history]  # before the scoring
    runs = [_run(tmp_path, "a", cmi, history), _run(tmp_path, "b", cmi, older)]
    assert rescore(runs[0], window_s=300.0)["window"]["with_self_best_threshold_f1"] == pytest.approx(
        [0.85, np.std([0.7, 0.8, 0.9, 1.0]), 4])  # the reports at 700-1000 s
    assert main([*map(str, runs), "--window", "300", "--mean", "--out", str(tmp_path / "r.json")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "| `a` | 4 | 0.850 ± 0.112 | – | – | 0.425 ± 0.056 |" in lines
    assert "| `b` | 4 | – | – | – | 0.425 ± 0.056 |" in lines
    assert "| mean ± sd of the runs' means (manipulation) | | 0.850 ± 0.000 (1) | – | – | 0.425 ± 0.000 (2) |" in lines


def test_graph_final_scores_the_final_graph_and_skips_runs_without_one(tmp_path: Path, capsys) -> None:
    truth = global_graph()
    run = _run(tmp_path, "with-final", np.where(truth > 0, 0.001, 0.3))  # the last live report: all wrong
    summary = json.loads((run / "summary.json").read_text())
    summary["final_graph"] = {"graph_env_steps": 5678, "threshold": 0.02, "true_graph": truth.tolist(),
                              "cmi": np.where(truth > 0, 0.3, 0.0).tolist()}
    (run / "summary.json").write_text(json.dumps(summary))
    final, last = rescore(run, graph="final"), rescore(run)
    assert final["env_steps"] == 5678 and final["f1"] == 1.0 and last["f1"] == 0.0
    without = _run(tmp_path, "without-final", np.where(truth > 0, 0.3, 0.0))
    assert main([str(run), str(without), "--graph", "final", "--out", str(tmp_path / "r.json")]) == 1
    assert "without-final/summary.json: no final graph" in capsys.readouterr().err
