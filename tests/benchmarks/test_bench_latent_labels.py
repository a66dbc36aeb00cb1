"""The latent-label cost benchmark at a toy size: both sides timed, the ratio and the bytes per step
printed and written, bad arguments refused."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.bench_latent_labels import main, parse_args

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_a_toy_run_prints_and_writes_both_rates(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "labels.json"
    main(["--batches", "1", "--rounds", "2", "--batch-steps", "16", "--slot-dim", "8", "--out", str(out)])
    result = json.loads(out.read_text())
    assert len(result["rounds"]) == 2 and result["num_slots"] == 5
    assert all(r["worker_steps_per_s"] > 0 and r["labeller_steps_per_s"] > 0 for r in result["rounds"])
    sizes = result["bytes_per_step"]
    assert sizes["frames"] > sizes["transitions"] > 0 and sizes["labels"] > 0
    assert "labeller / worker, median of 2 rounds" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [["--batches", "0"], ["--slot-dim", "6"]])
def test_bad_arguments_are_usage_errors(argv: list[str]) -> None:
    with pytest.raises(SystemExit) as info:
        parse_args(argv)
    assert info.value.code == 2
