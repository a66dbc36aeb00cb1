"""The slot-binding benchmark end to end at a toy budget: each budget trains, is scored and plotted."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.slot_binding import main


def test_slot_binding_toy_budget(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "binding.json"
    main(["--seeds", "0", "--num-objects", "2", "--train-frames", "40", "--eval-frames", "16", "--log-every", "2",
          "--budgets", "3", "4", "--out", str(out)])
    runs = json.loads(out.read_text())["results"][0]["runs"]
    assert [r["slot_updates"] for r in runs] == [3, 4]
    for r in runs:
        assert [u for u, _ in r["curve"]] == list(range(2, r["slot_updates"], 2)) + [r["slot_updates"]]
        assert -1.0 <= r["fg_ari"] <= 1.0 and 0.0 <= r["identity_slot_accuracy"] <= 1.0
    assert out.with_suffix(".png").stat().st_size > 0
    assert "| 3 |" in capsys.readouterr().out
    with pytest.raises(ValueError, match="budgets"):
        main(["--budgets", "0", "--out", str(tmp_path / "bad.json")])
