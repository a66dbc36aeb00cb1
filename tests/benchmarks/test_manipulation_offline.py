"""The fixed-dataset CDL benchmark: real robosuite shards, cached; each variant trains with its schedule."""
from __future__ import annotations

import argparse
import json

import pytest

from benchmarks.manipulation_offline import SCORES, main, parse_shard, shard_path, summarise


def test_shard_specs_are_checked() -> None:
    assert parse_shard("6000:3") == (6000, 3)
    for bad in ("6000", "a:1", "0:1", "-5:2"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_shard(bad)


def test_summary_averages_each_seeds_tail_then_the_seeds() -> None:
    def run(seed: int, f1s: list[float]) -> dict:
        points = [{"updates": 10 * (i + 1), **{k: f for k in SCORES}}
                  for i, f in enumerate(f1s)]
        return {"variant": "constant", "seed": seed, "curve": points}

    (row,) = summarise([run(0, [0.0, 0.4, 0.6]), run(1, [0.9, 0.6, 0.8])], tail=2)
    assert row["f1"]["per_seed"] == pytest.approx([0.5, 0.7])
    assert row["f1"]["mean"] == pytest.approx(0.6) and row["f1"]["std"] == pytest.approx(0.1414, abs=1e-3)
    assert row["updates"] == 30


def test_variants_train_on_the_same_cached_shards(tmp_path) -> None:
    out, cache = tmp_path / "offline.json", tmp_path / "data"
    argv = ["--shards", "150:1", "--heldout", "100:2", "--updates", "20", "--eval-every", "10", "--seeds", "0",
            "--feature-dim", "8", "--jobs", "1", "--lr", "1e-2", "--lr-final", "1e-4", "--cache", str(cache),
            "--out", str(out)]
    main(argv)
    result = json.loads(out.read_text())
    runs = {r["variant"]: r["curve"] for r in result["runs"]}
    assert [p["updates"] for p in runs["constant"]] == [10, 20] == [p["updates"] for p in runs["cosine"]]
    assert runs["constant"][-1]["lr"] == pytest.approx(1e-2)
    assert runs["cosine"][0]["lr"] == pytest.approx(1e-4 + 0.5 * (1e-2 - 1e-4))  # half-way down the cosine
    assert runs["cosine"][-1]["lr"] == pytest.approx(1e-4)
    assert all(0.0 <= p["f1"] <= 1.0 and 0.0 <= p["roc_auc"] <= 1.0 for c in runs.values() for p in c)
    assert out.with_suffix(".png").stat().st_size > 0
    shard = shard_path(cache, 150, 1)
    stamp = shard.stat().st_mtime_ns
    main(argv)  # a rerun reuses the collected shards
    assert shard.stat().st_mtime_ns == stamp
