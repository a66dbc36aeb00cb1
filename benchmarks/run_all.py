"""``make bench``: the fast benchmarks, each printing ratios against a baseline measured in the same run.

(c) time-to-F1 takes up to 15 minutes per graph: ``make bench-f1`` runs it.
"""
from __future__ import annotations

import subprocess
import sys

FAST = [["benchmarks.bench_cdl_update"], ["benchmarks.bench_cdl_update", "--objects", "10", "--width", "32"],
        ["benchmarks.bench_transport"], ["benchmarks.bench_transport", "--workers", "2"]]


def main() -> None:
    for args in FAST:
        print(f"\n=== python -m {' '.join(args)}", flush=True)
        subprocess.run([sys.executable, "-m", *args, *sys.argv[1:]], check=True)


if __name__ == "__main__":
    main()
