"""Soak (issue 20, item 8): a long ``causeway run`` with every kind of service (CDL on Chemical, PPO
with PredDiff, roles on the bus), its processes' resident memory and open file descriptors sampled
every few seconds; per process: the value at the end of the warm-up, the largest after it, and the
growth after it (least squares, MiB per hour). A restarted service shows as a new pid.

    python -m benchmarks.bench_soak [--minutes 60] [--warmup-minutes 5] [--out benchmark-results/soak.json]

The JSON keeps every sample (``series``) and a plot of resident memory over time is written beside it
(``soak.png``); each process's growth is also fitted over the second half alone, to tell a buffer
still filling from a leak.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from services.bus.router import free_tcp_port

RUN_FLAGS = ["--graph", "collider", "--num-objects", "3", "--collector", "ppo", "--intrinsic", "preddiff",
             "--evaluate", "false", "--progress", "false", "--metrics-base-port", "0",
             "--router-port", "0", "--worker-max-steps-per-second", "500"]


@dataclass(frozen=True)
class Sample:
    seconds: float
    rss_mib: float
    fds: int


@dataclass(frozen=True)
class Footprint:
    """One process over the soak, after the warm-up."""

    name: str
    pid: int
    samples: int
    rss_mib_at_warmup: float
    rss_mib_max: float
    rss_mib_per_hour: float
    """Least-squares slope of resident memory after the warm-up."""
    rss_mib_per_hour_second_half: float
    """The same slope over the second half of the time after the warm-up: near 0 once buffers are full."""
    fds_at_warmup: int
    fds_max: int


def sample(pid: int) -> tuple[float, int] | None:
    """Resident memory (MiB) and open file descriptors of ``pid``; None once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    rss_kib = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS"))
    return rss_kib / 1024, fds


def footprint(name: str, pid: int, samples: list[Sample], warmup_s: float) -> Footprint | None:
    """What ``samples`` (one process) say after ``warmup_s``; None without two samples after it."""
    after = [s for s in samples if s.seconds >= warmup_s]
    if len(after) < 2:
        return None
    t = np.array([s.seconds for s in after]) / 3600.0
    rss = np.array([s.rss_mib for s in after])
    late = t >= (t[0] + t[-1]) / 2
    return Footprint(name, pid, len(after), round(after[0].rss_mib, 1), round(float(rss.max()), 1),
                     round(_slope(t, rss), 1), round(_slope(t[late], rss[late]), 1),
                     after[0].fds, max(s.fds for s in after))


def _slope(t: np.ndarray, y: np.ndarray) -> float:
    return float(np.polyfit(t, y, 1)[0]) if len(t) >= 2 and np.ptp(t) > 0 else 0.0


def plot(series: dict[str, list[list[float]]], warmup_s: float, path: Path) -> None:
    """Resident memory of every process over the soak, one line each, the warm-up shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    for name, rows in sorted(series.items()):
        ax.plot([r[0] / 60 for r in rows], [r[1] for r in rows], label=name, lw=1.2)
    ax.axvspan(0, warmup_s / 60, color="0.9", label="warm-up")
    ax.set_xlabel("minutes")
    ax.set_ylabel("resident memory (MiB)")
    ax.set_title("Soak: resident memory per process")
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def processes(run_dir: Path, supervisor: int) -> dict[str, int]:
    try:
        table = json.loads((run_dir / "processes.json").read_text())
    except (OSError, ValueError):
        return {"supervisor": supervisor}
    return {"supervisor": supervisor, **{n: e["pid"] for n, e in table["processes"].items() if e.get("pid")}}


def soak(minutes: float, warmup_minutes: float, every_s: float, run_dir: Path) -> dict:
    cmd = [sys.executable, "-m", "services.cli", "run", *RUN_FLAGS, "--run-dir", str(run_dir),
           "--max-seconds", str(minutes * 60 + 60), "--dashboard-port", str(free_tcp_port())]
    stack = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    series: dict[tuple[str, int], list[Sample]] = {}
    started = time.monotonic()
    try:
        while time.monotonic() - started < minutes * 60 and stack.poll() is None:
            now = time.monotonic() - started
            for name, pid in processes(run_dir, stack.pid).items():
                found = sample(pid)
                if found is not None:
                    series.setdefault((name, pid), []).append(Sample(now, *found))
            time.sleep(every_s)
    finally:
        if stack.poll() is None:
            stack.send_signal(signal.SIGINT)
        out, _ = stack.communicate(timeout=600)
    summary = json.loads((run_dir / "summary.json").read_text()) if (run_dir / "summary.json").exists() else {}
    prints = [footprint(name, pid, s, warmup_minutes * 60) for (name, pid), s in series.items()]
    return {"minutes": minutes, "warmup_minutes": warmup_minutes, "sample_every_s": every_s, "flags": RUN_FLAGS,
            "returncode": stack.returncode, "env_steps": summary.get("env_steps"), "updates": summary.get("updates"),
            "restarts": summary.get("restarts"), "processes": [asdict(p) for p in prints if p is not None],
            "series": {f"{name} {pid}": [[round(s.seconds, 1), round(s.rss_mib, 2), s.fds] for s in samples]
                       for (name, pid), samples in series.items()},
            "tail": out[-2000:]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--warmup-minutes", type=float, default=5.0)
    parser.add_argument("--every-s", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=Path("benchmark-results/soak.json"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="soak-") as tmp:
        result = soak(args.minutes, args.warmup_minutes, args.every_s, Path(tmp) / "run")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    plot(result["series"], args.warmup_minutes * 60, args.out.with_suffix(".png"))
    print(f"{'process':<20} {'rss@warmup':>10} {'rss max':>8} {'MiB/h':>7} {'2nd half':>8} {'fds':>9}  "
          f"(env steps {result['env_steps']}, updates {result['updates']}, restarts {result['restarts']})")
    for p in result["processes"]:
        print(f"{p['name']:<20} {p['rss_mib_at_warmup']:>10} {p['rss_mib_max']:>8} {p['rss_mib_per_hour']:>7} "
              f"{p['rss_mib_per_hour_second_half']:>8} "
              f"{p['fds_at_warmup']:>4}-{p['fds_max']:<4}")


if __name__ == "__main__":
    main()
