"""The shared command line of the seeded table benchmarks: budget flags, seeds, partial saves, the table."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from benchmarks.seeded_table import table_main


@dataclasses.dataclass(frozen=True)
class Budget:
    train_frames: int = 4
    updates: int = 2


def test_budget_flags_seeds_and_partial_saves(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "deep" / "table.json"
    seen_on_disk: list[list[dict]] = []

    def run_seed(seed: int, budget: Budget, args, save) -> dict:
        save({"seed": seed, "partial": True})
        seen_on_disk.append(json.loads(out.read_text())["results"])
        return {"seed": seed, "frames": budget.train_frames, "updates": budget.updates, "scale": args.scale}

    def add(p) -> None:
        p.add_argument("--scale", type=float, default=1.0)

    results = table_main(["--seeds", "3", "5", "--train-frames", "7", "--scale", "0.5", "--out", str(out)],
                         description=None, budget_type=Budget, default_out=tmp_path / "unused.json",
                         run_seed=run_seed, table=lambda rs: f"{len(rs)} rows", add_arguments=add)
    assert results == [{"seed": s, "frames": 7, "updates": 2, "scale": 0.5} for s in (3, 5)]
    # the second seed's partial record was written beside the first seed's finished one
    assert seen_on_disk[1] == [results[0], {"seed": 5, "partial": True}]
    written = json.loads(out.read_text())
    assert written == {"budget": {"train_frames": 7, "updates": 2}, "results": results}
    assert capsys.readouterr().out.strip() == "2 rows"


def test_a_budget_flag_takes_integers_only(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        table_main(["--updates", "1.5", "--out", str(tmp_path / "t.json")], description=None, budget_type=Budget,
                   default_out=tmp_path / "t.json", run_seed=lambda *a: {}, table=str)
    assert not (tmp_path / "t.json").exists()


def test_merge_prints_one_table_over_earlier_runs_and_refuses_missing_files(tmp_path, capsys) -> None:
    out = tmp_path / "a.json"
    out.write_text(json.dumps({"budget": {}, "results": [{"seed": 0, "x": 1.0}, {"seed": 1, "x": 3.0}]}))
    records = table_main(["--merge", str(out), str(out)], description=None, budget_type=object,
                         default_out=tmp_path / "unused.json", run_seed=None,
                         table=lambda rs: f"{len(rs)} records, mean {sum(r['x'] for r in rs) / len(rs)}")
    assert len(records) == 4 and "4 records, mean 2.0" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        table_main(["--merge", str(tmp_path / "missing.json")], description=None, budget_type=object,
                   default_out=out, run_seed=None, table=str)
