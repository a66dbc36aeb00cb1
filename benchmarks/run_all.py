"""``make bench``: the fast benchmarks, each printing ratios against a baseline measured in the same run.

The long ones have their own targets: time-to-F1 (up to 15 minutes per graph, ``make bench-f1``),
the collection comparison (``make bench-collection``, ~1 h), the chapter-3 generalisation tables
(``make bench-ch3``, ~33 min), the manipulation contact diagnostics
(``python -m benchmarks.manipulation_contacts --run-dir RUN``, needs a manipulation run) and CDL
training settings on one fixed manipulation dataset (``python -m benchmarks.manipulation_offline``, ~46 min
with its shards cached, ~12 more to collect them). ``python -m benchmarks.rescore_runs RUN...`` scores
finished runs again from their ``summary.json`` (Table 3.1's scoring beside ours), and
``python -m benchmarks.cmi_estimation --run-dir RUN`` scores a run's model under each CMI estimation choice.
"""
from __future__ import annotations

import subprocess
import sys

FAST = [["benchmarks.bench_cdl_update"], ["benchmarks.bench_cdl_update", "--objects", "10", "--width", "32"],
        ["benchmarks.bench_transport"], ["benchmarks.bench_transport", "--workers", "2"],
        ["benchmarks.bench_masked_outputs"], ["benchmarks.bench_masked_outputs", "--graph", "chain"],
        ["benchmarks.bench_env_worker", "--env", "chemical", "--batch-steps", "256"],
        ["benchmarks.bench_env_worker", "--env", "manipulation", "--seconds", "20"]]


def main() -> None:
    for args in FAST:
        print(f"\n=== python -m {' '.join(args)}", flush=True)
        subprocess.run([sys.executable, "-m", *args, *sys.argv[1:]], check=True)


if __name__ == "__main__":
    main()
