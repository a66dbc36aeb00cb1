"""``causeway compare``: the results contract's scores of finished runs side by side, per run or as
mean ± sample sd per configuration; bad paths refused before anything is printed or written."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from services.supervisor.compare import CONTRACT, ERROR, columns, contract_scores, group, group_table, load_run, main

REPO = Path(__file__).resolve().parents[2]


def _summary(method: str, env: str, seed: int, options: dict | None = None, **blocks: dict) -> dict:
    return {"run_id": f"{method}-{env}-s{seed}", "method": method, "env": env, "seed": seed,
            "env_options": options or {}, "accuracy": 0.5, **blocks}


def _write(root: Path, content: dict) -> Path:
    run = root / f"{content['run_id']}-{len(list(root.glob('*')))}"
    run.mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps(content))
    return run


def test_contract_scores_take_every_block_the_summary_has_and_nothing_else() -> None:
    summary = _summary("cdl", "chemical", 0, graph={"accuracy": 0.9, "f1": 0.8, "best_threshold_f1": 0.85,
                                                    "roc_auc": 0.95, "precision": 0.7},
                       task={"return_mean": -2.5, "success_rate": None, "episodes": 100},
                       slots={"error": "no checkpoint"}, local_graph="not a block")
    scores = contract_scores(summary)
    assert scores == {"graph.accuracy": 0.9, "graph.f1": 0.8, "graph.best_threshold_f1": 0.85, "graph.roc_auc": 0.95,
                      "task.return_mean": -2.5, "slots.fg_ari": ERROR}
    assert "accuracy" not in scores and "graph.precision" not in scores  # top-level legacy keys, non-contract keys
    every = {f"{b}.{k}" for b, keys in CONTRACT for k in keys}
    assert {"final_graph.best_threshold_f1", "local_graph.pr_auc", "task.stages_mean", "slots.fg_ari",
            "latent_actions.dci_i", "latent_actions.psnr"} <= every


def test_runs_of_one_configuration_fold_into_mean_and_sample_sd(tmp_path) -> None:
    options = {"graph": "chain", "num_objects": 3}
    runs = [load_run(_write(tmp_path, _summary("cdl", "chemical", s, options, graph={"f1": f1, "roc_auc": 1.0})))
            for s, f1 in ((0, 0.9), (1, 0.8), (2, 1.0))]
    runs.append(load_run(_write(tmp_path, _summary("cdl", "chemical", 0, {"graph": "full", "num_objects": 3},
                                                   graph={"f1": 0.5}))))
    runs.append(load_run(_write(tmp_path, _summary("elden", "thawing", 0, {"task": "thaw-fish"},
                                                   local_graph={"roc_auc": 0.85, "pr_auc": 0.2, "best_f1": 0.3},
                                                   task={"success_rate": 0.1, "stages_mean": 0.6}))))
    groups = group(runs)
    assert [(g.method, g.env, g.setting, len(g.runs)) for g in groups] == [
        ("cdl", "chemical", "graph=chain num_objects=3", 3), ("cdl", "chemical", "graph=full num_objects=3", 1),
        ("elden", "thawing", "task=thaw-fish", 1)]
    chain = groups[0]
    assert chain.mean["graph.f1"] == pytest.approx(0.9, rel=1e-12)
    assert chain.sd["graph.f1"] == pytest.approx(0.1, rel=1e-9)  # sample sd: sqrt((0.01 + 0 + 0.01) / 2)
    assert chain.count == {"graph.f1": 3, "graph.roc_auc": 3} and groups[1].sd["graph.f1"] == 0.0
    assert columns(runs) == ["graph.f1", "graph.roc_auc", "local_graph.roc_auc", "local_graph.pr_auc",
                             "local_graph.best_f1", "task.success_rate", "task.stages_mean"]
    table = group_table(groups).splitlines()
    assert table[2].startswith("| cdl | chemical (graph=chain num_objects=3) | 3 | 0, 1, 2 | 0.900 ± 0.100 | "
                               "1.000 ± 0.000")
    assert table[4].endswith("|  |  | 0.850 | 0.200 | 0.300 | 0.100 | 0.600 |")


def test_a_score_only_some_runs_of_a_configuration_have_says_how_many(tmp_path) -> None:
    runs = [load_run(_write(tmp_path, _summary("dyno", "chemical-pixels", 0, slots={"fg_ari": 0.9}))),
            load_run(_write(tmp_path, _summary("dyno", "chemical-pixels", 1, slots={"error": "failed"})))]
    (g,) = group(runs)
    assert g.count == {"slots.fg_ari": 1} and "| 0.900 (1) |" in group_table([g])


def test_the_command_prints_the_table_writes_plot_and_json(tmp_path, capsys) -> None:
    a = _write(tmp_path, _summary("cdl", "chemical", 0, final_graph={"accuracy": 0.99, "f1": 0.95}))
    b = _write(tmp_path, _summary("flam", "multigrid-agents", 0, latent_actions={"dci_d": 0.7, "psnr": 57.1}))
    out_png, out_json = tmp_path / "out" / "c.png", tmp_path / "out" / "c.json"
    assert main([str(a), str(b / "summary.json"), "--plot", str(out_png), "--json", str(out_json)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == ("| run | method | env | seed | final_graph.accuracy | final_graph.f1 | latent_actions.dci_d "
                        "| latent_actions.psnr |")
    assert lines[2] == "| cdl-chemical-s0 | cdl | chemical | 0 | 0.990 | 0.950 |  |  |"
    assert lines[3] == "| flam-multigrid-agents-s0 | flam | multigrid-agents | 0 |  |  | 0.700 | 57.100 |"
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = json.loads(out_json.read_text())
    assert rows["columns"] == ["final_graph.accuracy", "final_graph.f1", "latent_actions.dci_d", "latent_actions.psnr"]
    assert [r["scores"] for r in rows["runs"]] == [{"final_graph.accuracy": 0.99, "final_graph.f1": 0.95},
                                                    {"latent_actions.dci_d": 0.7, "latent_actions.psnr": 57.1}]
    assert main([str(a), "--mean", "--json", str(out_json)]) == 0
    assert json.loads(out_json.read_text())["groups"][0]["count"] == {"final_graph.accuracy": 1, "final_graph.f1": 1}


def test_bad_runs_are_refused_with_their_paths_and_nothing_is_written(tmp_path) -> None:
    good = _write(tmp_path, _summary("cdl", "chemical", 0, graph={"f1": 1.0}))
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "summary.json").write_text("{not json")
    (tmp_path / "other.json").write_text(json.dumps({"f1": 1.0}))
    out_json = tmp_path / "rows.json"
    cmd = [sys.executable, "-m", "services.cli", "compare", str(good), str(tmp_path / "missing"),
           str(tmp_path / "broken"), str(tmp_path / "other.json"), "--json", str(out_json)]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == "" and not out_json.exists()
    errors = done.stderr.splitlines()
    assert len(errors) == 3 and "missing: no summary.json" in errors[0]
    assert "broken/summary.json: not a readable summary" in errors[1] and "other.json: not a run summary" in errors[2]
    scoreless = _write(tmp_path, _summary("modular", "chemical", 0))
    assert main([str(scoreless)]) == 2


def test_a_nan_score_is_left_out_not_averaged() -> None:
    scores = contract_scores(_summary("cdl", "chemical", 0, graph={"f1": math.nan, "roc_auc": True, "accuracy": 1}))
    assert scores == {"graph.accuracy": 1.0}
