"""Fig. 4.8's benchmark on a budget of seconds: the abstractions it compares, SAC behind each one's
mask in and out of distribution, and the files it writes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks import cbm_sac_abstraction as bench
from envs.registry import make_env

SCENE = dict(graph="full", num_objects=3, distractors="2,2", task="match-first")
TINY = bench.SACRun(steps=80, warmup=40, hidden=16, batch_size=16, eval_every=40, curve_episodes=2, eval_episodes=4)
NAMES = make_env("chemical-distractors", **SCENE).unwrapped.factor_names


def table_json(path: Path) -> Path:
    """A cbm_table.json as benchmarks.cbm_graph_table writes it (only what this benchmark reads)."""
    rows = [{"variant": "implicit", "seed": 0, "kept": {"truth": [0, 9], "cbm": [0, 4, 9, 12], "cbm_true_reward": [0, 9],
                                                         "cdl": [0, 3, 6, 12, 13]}},
            {"variant": "explicit", "seed": 0, "kept": {"truth": [0, 9], "cbm": [0, 9], "cbm_true_reward": [0, 9],
                                                         "cdl": [0, 3, 6, 12]}}]
    path.write_text(json.dumps({"factor_names": list(NAMES), "rows": rows}))
    return path


def test_conditions_take_cbm_from_the_implicit_model_and_cdl_from_the_explicit_one_with_goals(tmp_path: Path) -> None:
    kept = bench.abstractions_from_table(table_json(tmp_path / "t.json"), 0, NAMES)
    assert kept["full"] == list(range(len(NAMES))) == list(range(16))
    assert kept["cbm"] == [0, 4, 9, 12] and kept["cbm_true_reward"] == kept["true_minimal"] == [0, 9]
    assert kept["cdl"] == [0, 3, 6, 9, 10, 11, 12]  # CDL's abstraction of its graph, the goals provided
    with pytest.raises(ValueError, match="seed 1"):
        bench.abstractions_from_table(tmp_path / "t.json", 1, NAMES)
    with pytest.raises(ValueError, match="other factors"):
        bench.abstractions_from_table(tmp_path / "t.json", 0, NAMES[:-1])


def test_a_policy_behind_the_minimal_abstraction_behaves_identically_out_of_distribution() -> None:
    """With only obj0's colour and goal visible, lifting the distractors out of range and scaling the
    positions up changes nothing the policy sees: the same episodes give the same success and return.
    The full-state policy sees the change (its Q-values move)."""
    minimal = bench.run_condition(({**SCENE, "episode_length": 5}, "cbm_true_reward", [0, 9], TINY, 0))
    assert [p["env_steps"] for p in minimal["curve"]] == [40, 80]
    assert minimal["id"] == minimal["ood_distractors"] == minimal["ood_all"]
    assert 0.0 <= minimal["id"]["success"] <= 1.0
    full = bench.make_agent(SCENE, list(range(len(NAMES))), TINY, 0)
    env_id, env_ood = (make_env("chemical-distractors", **SCENE, **extra) for extra in (bench.SETTINGS["id"],
                                                                                        bench.SETTINGS["ood_all"]))
    obs_id, obs_ood = env_id.reset(seed=3)[0], env_ood.reset(seed=3)[0]
    np.testing.assert_array_equal(obs_id[[0, 9]], obs_ood[[0, 9]])
    q_id, q_ood = (full.q_values(torch.from_numpy(o[None])) for o in (obs_id, obs_ood))
    assert not torch.allclose(q_id, q_ood)


def test_main_writes_rows_table_and_figure(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    bench.main(["--distractors", "2,2", "--abstractions", str(table_json(tmp_path / "t.json")), "--seeds", "0",
                "--conditions", "full", "cbm", "--episode-length", "5", "--out", str(out),
                *[f"--{k.replace('_', '-')}={v}" for k, v in vars(TINY).items()]])
    result = json.loads((out / "cbm_sac.json").read_text())
    assert [r["condition"] for r in result["rows"]] == ["full", "cbm"] and result["run"]["steps"] == 80
    assert result["rows"][1]["kept"] == [0, 4, 9, 12]
    assert (out / "cbm_sac.png").stat().st_size > 1000
    assert "| cbm | 1 | 4.0 |" in capsys.readouterr().out


def test_abstractions_learned_in_process_have_every_condition_and_the_truth() -> None:
    """The path without a Table 4.1 run: both models trained here (3 updates: only the shapes count)."""
    scene = dict(graph="full", num_objects=2, distractors="1,1", task="match-first")
    kept = bench.abstractions_from_training(scene, steps=200, updates=3, seed=0)
    assert set(kept) == set(bench.CONDITIONS) | {"true_minimal"}
    assert kept["full"] == list(range(10)) and kept["true_minimal"] == [0, 6]  # obj0.color, obj0.goal_color
    assert {6, 7} <= set(kept["cdl"]) and set(kept["cbm"]) <= set(range(10))
