"""Table 4.1's benchmark, ``--reward-only`` (issue 19): the causal reward model trained alone on the
table's data, its reward parents with the model's CMI and with the per-mask-variance CMI it replaced."""
from __future__ import annotations

import json
from pathlib import Path

from benchmarks.cbm_graph_table import main


def test_reward_only_writes_both_estimators_and_the_data_it_saw(tmp_path: Path) -> None:
    main(["--num-objects", "2", "--distractors", "1,1", "--task", "match-first", "--reward-only", "--steps", "400",
          "--updates", "60", "--estimate-every", "30", "--seeds", "0", "--out", str(tmp_path)])
    out = json.loads((tmp_path / "cbm_reward.json").read_text())
    row, names = out["rows"][0], out["factor_names"]
    assert len(row["reward"]["cmi"]) == len(names) + 1 == len(row["per_mask_reward"]["learned"])
    assert 0.0 < row["data"]["nonzero_share"] < 1.0 and row["data"]["distinct_values"] == 2
    assert [t["update"] for t in row["trace"]] == [30, 60]
    for key in ("reward", "per_mask_reward"):
        assert 0.0 <= row[key]["f1"] <= 1.0 and 0.0 <= row[key]["abstraction_accuracy_true_graph"] <= 1.0
    assert row["reward"]["learned"] == [int(c >= 0.01) for c in row["reward"]["cmi"]] or \
        any(abs(c - 0.01) < 1e-4 for c in row["reward"]["cmi"])  # parents are the CMI at the threshold (rounded)
