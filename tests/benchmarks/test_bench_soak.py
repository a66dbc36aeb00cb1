"""The soak benchmark's arithmetic: growth after the warm-up, and over its second half alone."""
from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.bench_soak import Sample, footprint, plot


def test_a_buffer_that_fills_then_stops_shows_no_late_growth(tmp_path: Path) -> None:
    # 60 MiB/h for the first 30 min after a 5-min warm-up, then flat for 30 min; 10 s samples
    samples = []
    for k in range(0, 65 * 6 + 1):
        t = 10.0 * k
        grown = min(max(t - 300.0, 0.0), 1800.0) / 3600.0 * 60.0
        samples.append(Sample(t, 400.0 + grown, 20 + (k == 100)))
    fp = footprint("dynamics-learner", 7, samples, warmup_s=300.0)
    assert fp is not None
    assert fp.rss_mib_at_warmup == pytest.approx(400.0)
    assert fp.rss_mib_max == pytest.approx(430.0)
    assert 15.0 < fp.rss_mib_per_hour < 60.0
    assert abs(fp.rss_mib_per_hour_second_half) < 1.0
    assert (fp.fds_at_warmup, fp.fds_max) == (20, 21)
    plot({"dynamics-learner 7": [[s.seconds, s.rss_mib, s.fds] for s in samples]}, 300.0, tmp_path / "soak.png")
    assert (tmp_path / "soak.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_process_seen_once_after_the_warm_up_has_no_footprint() -> None:
    assert footprint("env-worker", 3, [Sample(0.0, 1.0, 1), Sample(400.0, 1.0, 1)], warmup_s=300.0) is None
