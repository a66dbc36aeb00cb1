"""The household benchmark runs end to end on a few steps and prints one row per environment."""
from __future__ import annotations

import pytest

from benchmarks.bench_household import ENVS, main


def test_benchmark_prints_a_row_per_environment(capsys: pytest.CaptureFixture[str]) -> None:
    main(steps=300, seeds=2)
    rows = capsys.readouterr().out.strip().splitlines()
    assert len(rows) == 1 + len(ENVS)
    for name, row in zip(ENVS, rows[1:]):
        assert row.startswith(name) and row.split()[-2] == "1.00"
