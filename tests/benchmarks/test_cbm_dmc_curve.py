"""Fig. 4.7's DMC benchmark: the conditions' input masks (the oracle keeps the scene, drops the
distractors), a short run's curve, table and plot, and abstractions from another env refused."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.cbm_dmc_curve import kept_factors, main


def test_a_short_run_writes_curves_per_condition(tmp_path: Path) -> None:
    main(["--distractors", "2,2", "--episode-length", "20", "--steps", "60", "--warmup", "30",
          "--eval-every", "30", "--eval-episodes", "1", "--conditions", "full", "true", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "cbm_dmc.json").read_text())["rows"]
    kept = {r["condition"]: r["kept"] for r in rows}
    assert kept == {"full": list(range(28)), "true": list(range(24))}  # walker: 24 scene factors, 4 distractors
    for row in rows:
        assert [p["env_steps"] for p in row["curve"]] == [30, 60]
        assert all(0.0 <= p["return"] <= 20.0 for p in row["curve"])  # the suite's reward is in [0, 1] per step
    assert (tmp_path / "cbm_dmc.png").stat().st_size > 0


def test_abstractions_of_another_env_are_refused(tmp_path: Path) -> None:
    table = tmp_path / "cbm_table.json"
    table.write_text(json.dumps({"factor_names": ["a", "b"], "rows": []}))
    with pytest.raises(ValueError, match="other factors"):
        kept_factors("dmc-cheetah", {"distractors": "1,1"}, table, 0)
    names = kept_factors("dmc-cheetah", {"distractors": "1,1"}, None, 0)
    assert names == {"full": list(range(19)), "true": list(range(17))}


def test_cbm_and_cdl_abstractions_come_from_a_table_run(tmp_path: Path) -> None:
    from envs.registry import make_env

    env = make_env("dmc-cheetah", distractors="1,1").unwrapped
    names = list(env.factor_names)
    env.close()
    rows = [{"variant": "implicit", "seed": 0, "kept": {"cbm": [0, 1], "cdl": [5]}},
            {"variant": "explicit", "seed": 0, "kept": {"cbm": [3], "cdl": [2, 4]}}]
    table = tmp_path / "cbm_table.json"
    table.write_text(json.dumps({"factor_names": names, "rows": rows}))
    kept = kept_factors("dmc-cheetah", {"distractors": "1,1"}, table, 0)
    assert kept["cbm"] == [0, 1] and kept["cdl"] == [2, 4]  # CBM's implicit graph, CDL's explicit one
    assert set(kept_factors("dmc-cheetah", {"distractors": "1,1"}, table, 1)) == {"full", "true"}
