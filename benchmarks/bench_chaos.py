"""Chaos to the target (issue 20 item 4): a real ``causeway run`` that must reach its target graph score
while each kind of service is SIGKILLed in turn, against the same run left alone.

Two runs of one configuration (:func:`benchmarks.chaos_stack.command`: CDL on Chemical, collider, 3
objects, PPO with PredDiff so all six kinds of service run, one worker at 500 steps/s, checkpoints every
2 s) with ``--target-f1``: first the baseline, untouched; then the chaos run, in which env-worker,
dynamics-learner, graph-evaluator, intrinsic-reward, policy-learner and dashboard are SIGKILLed one after
the other (each at least ``--kill-every-s`` after the one before, and only once the one before has
recovered), and with ``--kill-supervisor`` the supervisor too, the same command then started again on
the same run directory. Per kill: seconds until the restarted process is back on the bus, seconds
until the run moves again (env steps, updates, and a graph report from newer weights), transitions
lost as the learner counts them (``lost_steps``, its seq-gap count, over the kill) and, for the
worker, the steps it had stepped but not published. Per run: seconds from start to exit, whether
and why it stopped, the summary's ``transitions_lost``.

    nice -n 19 python -m benchmarks.bench_chaos [--target 0.9] [--metric f1] [--max-seconds 900]
        [--kill-every-s 20] [--kill-supervisor] [--skip-baseline] [--out benchmark-results/chaos]
        [causeway run flags for both runs, last wins: --worker-max-steps-per-second 60 ...]

Writes ``<out>/chaos.json`` and prints the table (markdown).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

from benchmarks.chaos_stack import KINDS, Bus, command, kill_and_recover, pid_alive, start, stop, table
from services.bus.router import free_tcp_port
from tests.waiting import wait_for

KILL_FIELDS = ("back_on_bus_s", "run_recovered_s", "learner_counted_lost_steps", "transitions_lost",
               "transitions_lost_at_least", "services_gone_s", "left_running_60s_after")


def run_row(summary: dict[str, Any], seconds: float) -> dict[str, Any]:
    """One run's line: wall seconds from the first start to the exit, and what its summary says."""
    stopped = str(summary.get("stopped_because", "no summary"))
    lost = summary.get("transitions_lost", {})
    return {"seconds": round(seconds, 1), "stopped_because": stopped, "target_reached": stopped.startswith("target"),
            "env_steps": int(summary.get("env_steps", 0)), "updates": int(summary.get("updates", 0)),
            "restarts": int(summary.get("restarts", 0)), "f1": summary.get("f1"),
            "lost_batches": int(lost.get("batches", 0)), "lost_steps": int(lost.get("steps", 0))}


def build_table(baseline: dict[str, Any] | None, chaos: dict[str, Any], kills: list[dict[str, Any]]) -> dict[str, Any]:
    """The benchmark's result: the kills (their figures), both runs, and the chaos run's time to
    target over the baseline's (None unless both reached it)."""
    rows = [{"killed": k["service"], **{f: k[f] for f in KILL_FIELDS if f in k},
             **({"note": k["note"]} if "note" in k else {})} for k in kills]
    both = baseline is not None and baseline["target_reached"] and chaos["target_reached"]
    return {"kills": rows, "baseline": baseline, "chaos": chaos,
            "slowdown": round(chaos["seconds"] / baseline["seconds"], 2) if both else None,
            "extra_seconds": round(chaos["seconds"] - baseline["seconds"], 1) if both else None}


def _cell(value: Any) -> str:
    return "-" if value is None else f"{value:,}" if isinstance(value, int) else str(value)


def format_table(result: dict[str, Any]) -> str:
    """Markdown: one line per kill, then one per run."""
    lines = ["| killed | back on the bus (s) | run moving again (s) | steps lost (learner's count) | notes |",
             "|---|---|---|---|---|"]
    for k in result["kills"]:
        notes = []
        if "transitions_lost" in k:
            notes.append(f"not in the resumed checkpoint: {k['transitions_lost']:,} steps")
        if "transitions_lost_at_least" in k:
            notes.append(f"stepped, not published: {k['transitions_lost_at_least']:,} steps")
        if k.get("left_running_60s_after"):
            notes.append(f"still running 60 s after the supervisor's SIGKILL: {', '.join(k['left_running_60s_after'])}")
        notes += [k["note"]] if "note" in k else []
        lines.append(f"| {k['killed']} | {_cell(k.get('back_on_bus_s'))} | {_cell(k.get('run_recovered_s'))} | "
                     f"{_cell(k.get('learner_counted_lost_steps'))} | {'; '.join(notes)} |")
    lines += ["", "| run | seconds to exit | stopped because | env steps | updates | restarts | lost batches / steps |",
              "|---|---|---|---|---|---|---|"]
    for name in ("baseline", "chaos"):
        r = result[name]
        if r is not None:
            lines.append(f"| {name} | {r['seconds']} | {r['stopped_because']} | {r['env_steps']:,} | {r['updates']:,} | "
                         f"{r['restarts']} | {r['lost_batches']:,} / {r['lost_steps']:,} |")
    if result["slowdown"] is not None:
        lines.append(f"\nchaos run to target: {result['extra_seconds']:+} s ({result['slowdown']}x the baseline)")
    return "\n".join(lines)


class Stack:
    """One run of the benchmark's command: its process, ports, and a client of its router."""

    def __init__(self, run_dir: Path, flags: tuple[str, ...], max_seconds: float) -> None:
        self.run_dir, self.port, self.dashboard = run_dir, free_tcp_port(), free_tcp_port()
        self.cmd = command(run_dir, self.port, 0, self.dashboard, extra=flags, max_seconds=max_seconds)
        self.started = time.monotonic()
        self.proc = start(self.cmd)
        self.bus: Bus | None = None

    def connect(self) -> Bus:
        if self.bus is not None:
            self.bus.close()
        self.bus = Bus(f"tcp/127.0.0.1:{self.port}", self.run_dir, self.run_dir.name)  # the run id: its folder's name
        return self.bus

    def ended(self) -> bool:
        return self.proc.poll() is not None

    def finish(self, timeout: float) -> dict[str, Any]:
        """Wait for the run to end by itself; the run's line."""
        try:
            out, _ = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            out = stop(self.proc, self.run_dir)
        seconds = time.monotonic() - self.started
        if self.bus is not None:
            self.bus.close()
        (self.run_dir / "supervisor.out").write_text(out or "")
        try:
            summary = json.loads((self.run_dir / "summary.json").read_text())
        except (OSError, ValueError):
            summary = {}
        return run_row(summary, seconds)


def wait_until_running(stack: Stack) -> Bus:
    wait_for(lambda: stack.ended() or set(KINDS) <= set(table(stack.run_dir).get("processes", {})), 180,
             "every service started")
    bus = stack.connect()
    wait_for(lambda: stack.ended() or (bus.seen.reports and all(bus.seen.of(k.rsplit("-", 1)[0] if k.startswith("env-")
                                                                           else k) for k in KINDS)),
             300, "a graph report and a beat from every service")
    wait_for(lambda: stack.ended() or (stack.run_dir / "checkpoints" / "dynamics-learner-0.pt").exists(), 60,
             "a learner checkpoint")
    return bus


def kill_each(stack: Stack, bus: Bus, every_s: float) -> list[dict[str, Any]]:
    kills: list[dict[str, Any]] = []
    last = time.monotonic()
    for name in KINDS:
        while time.monotonic() - last < every_s and not stack.ended():
            time.sleep(0.5)
        if stack.ended():
            kills.append({"service": name, "note": "not killed: the run had ended"})
            continue
        figures: dict[str, Any] = {}
        try:
            kill_and_recover(bus, stack.run_dir, name, stack.dashboard, figures)
        except AssertionError as exc:
            if not stack.ended():
                raise
            figures["note"] = f"the run ended before its recovery was seen ({exc})"
        kills.append(figures)
        print(json.dumps(figures), flush=True)
        last = time.monotonic()
    return kills


def kill_supervisor(stack: Stack) -> dict[str, Any]:
    """SIGKILL the supervisor; wait for its services to die with it; start the same command on the same
    run directory; the seconds until the learner is back on the bus and training."""
    services = {n: e["pid"] for n, e in table(stack.run_dir).get("processes", {}).items() if e.get("pid")}
    killed_at = time.time()
    stack.proc.send_signal(signal.SIGKILL)
    stack.proc.wait(30)
    with contextlib.suppress(AssertionError):
        wait_for(lambda: not any(pid_alive(p) for p in services.values()), 60, "every service to die with the supervisor")
    left = sorted(n for n, p in services.items() if pid_alive(p))
    for name in left:  # what did not die with its supervisor would hold the run's ports and checkpoints
        os.kill(services[name], signal.SIGKILL)
    figures: dict[str, Any] = {"service": "supervisor", "services_gone_s": round(time.time() - killed_at, 1),
                               "left_running_60s_after": left}
    stack.proc = start(stack.cmd)
    wait_for(lambda: stack.ended() or table(stack.run_dir).get("supervisor_pid") == stack.proc.pid, 120,
             "the second supervisor's process table")
    bus = stack.connect()
    first = wait_for(lambda: bus.seen.of("dynamics-learner", after=killed_at), 180, "the learner after the restart")[0]
    figures["back_on_bus_s"] = round(first.timestamp - killed_at, 1)
    wait_for(lambda: bus.seen.rising("dynamics-learner", "updates", killed_at), 180, "learner updates after the restart")
    wait_for(lambda: bus.seen.reports_after(killed_at), 180, "a graph report after the restart")
    figures["run_recovered_s"] = round(time.time() - killed_at, 1)
    figures["learner_counted_lost_steps"] = int(bus.seen.latest("dynamics-learner", "lost_steps"))
    figures["note"] = f"the same command again; the learner resumed at update {int(first.values.get('resumed_at_update', 0))}"
    return figures


def chaos_run(out: Path, flags: tuple[str, ...], args: argparse.Namespace) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    stack = Stack(out / "chaos", flags, args.max_seconds)
    kills: list[dict[str, Any]] = []
    try:
        bus = wait_until_running(stack)
        kills = kill_each(stack, bus, args.kill_every_s)
        if args.kill_supervisor and not stack.ended():
            time.sleep(args.kill_every_s)
            kills.append(kill_supervisor(stack))
            print(json.dumps(kills[-1]), flush=True)
        return stack.finish(args.max_seconds + 300), kills
    finally:
        if not stack.ended():
            stop(stack.proc, stack.run_dir)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--target", type=float, default=0.9, help="--target-f1 of both runs")
    p.add_argument("--metric", default="f1", help="--target-metric of both runs")
    p.add_argument("--max-seconds", type=float, default=900.0)
    p.add_argument("--kill-every-s", type=float, default=20.0)
    p.add_argument("--kill-supervisor", action="store_true")
    p.add_argument("--skip-baseline", action="store_true")
    p.add_argument("--out", default=f"benchmark-results/chaos-{time.strftime('%Y%m%d-%H%M%S')}")
    args, extra = p.parse_known_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    flags = ("--target-f1", str(args.target), "--target-metric", args.metric, *extra)
    baseline = None
    if not args.skip_baseline:
        base = Stack(out / "baseline", flags, args.max_seconds)
        baseline = base.finish(args.max_seconds + 300)
        print("baseline:", json.dumps(baseline), flush=True)
    chaos, kills = chaos_run(out, flags, args)
    result = build_table(baseline, chaos, kills)
    result["run_command"] = " ".join(command(Path("RUN_DIR"), 0, 0, 0, extra=flags, max_seconds=args.max_seconds))
    result["load_average_1_5_15"] = [round(x, 1) for x in os.getloadavg()]
    (out / "chaos.json").write_text(json.dumps(result, indent=1))
    print(format_table(result))


if __name__ == "__main__":
    main()
