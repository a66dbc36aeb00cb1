"""Chaos (issue 20, item 4): SIGKILL each kind of service mid-run, then the supervisor itself.

A real ``causeway run`` (router, supervisor and every service as processes on loopback; CDL on
Chemical, PPO with the prediction-difference intrinsic reward, so all six kinds of service run). Each
kind is killed in turn; the supervisor must restart it, the run must go on (env steps, learner
updates and graph reports keep coming), a restarted learner must resume from its checkpoint with
versions above any it published and its update count not overcounted, and the run must still reach
its target and end with a summary. The supervisor killed: every service dies with it
(PR_SET_PDEATHSIG), nothing is left, and the same command on the same run directory resumes. A
stalled learner (SIGSTOP) stalls nothing else, its memory stays bounded, and what it received plus
what it counted lost (seq gaps) matches what the worker published, up to what is in flight. Recovery
times and transitions lost are written to ``test-artifacts/chaos/``; the stack driver is
:mod:`benchmarks.chaos_stack`, shared with ``benchmarks/bench_chaos.py`` (the table in docs/operating.md).
"""
from __future__ import annotations

import json
import os
import signal
import time
import urllib.request
from pathlib import Path

import pytest

from benchmarks.chaos_stack import (BATCH_STEPS, KINDS, REPO, Bus, command, kill_and_recover, pid_alive, start, stop,
                                    table)
from services.bus.router import free_tcp_port
from tests.waiting import wait_for

pytestmark = [pytest.mark.integration, pytest.mark.slow]
ARTIFACTS = REPO / "test-artifacts" / "chaos"
ARTIFACTS = REPO / "test-artifacts" / "chaos"


TO_TARGET = ("--num-objects", "10", "--target-f1", "0.85", "--target-metric", "f1")
"""A run that needs minutes to its target (F1 0.88 came at ~1,600 updates in a 15-minute run on a
loaded 2-core machine), so that every kill and recovery happens before it (3 objects reach F1 1.0 at
the first reports; best-threshold F1 0.95 came at ~700 updates, before the policy-learner's recovery)."""


def test_each_service_killed_in_turn_is_restarted_and_the_run_reaches_its_target(tmp_path: Path) -> None:
    run_dir, port, dashboard = tmp_path / "run", free_tcp_port(), free_tcp_port()
    metrics = 21000 + (os.getpid() % 1500) * 20
    stack = start(command(run_dir, port, metrics, dashboard, extra=TO_TARGET))
    bus, figures = None, []
    try:
        wait_for(lambda: set(KINDS) <= set(table(run_dir).get("processes", {})), 90, "every service started")
        bus = Bus(f"tcp/127.0.0.1:{port}", run_dir, "run")
        wait_for(lambda: bus.seen.reports and all(bus.seen.of(k.rsplit("-", 1)[0] if k.startswith("env-") else k) for k in KINDS),
                 240, "a graph report and a beat from every service")
        wait_for(lambda: (run_dir / "checkpoints" / "dynamics-learner-0.pt").exists(), 60, "a learner checkpoint")
        for name in KINDS:
            figures.append(kill_and_recover(bus, run_dir, name, dashboard))
        wait_for(lambda: stack.poll() is not None, 900, "the run to stop by itself (its target or its budget)")
        max_updates = max(b.values.get("updates", 0) for b in bus.seen.of("dynamics-learner"))
    finally:
        out = stop(stack, run_dir)
        if bus is not None:
            bus.close()
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "figures.json").write_text(json.dumps({"kills": figures}, indent=1))
        print(json.dumps(figures, indent=1))
    assert stack.returncode == 0, out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts"] == len(KINDS)
    assert 0 < summary["updates"] <= max_updates + 50, (summary["updates"], max_updates)  # not the lives summed
    assert summary["stopped_because"].startswith("target"), summary["stopped_because"]
    assert summary["transitions_lost"]["steps"] >= 0


def test_a_killed_supervisor_takes_its_services_with_it_and_the_run_resumes(tmp_path: Path) -> None:
    run_dir, port, dashboard = tmp_path / "run", free_tcp_port(), free_tcp_port()
    metrics = 23000 + (os.getpid() % 1500) * 20
    cmd = command(run_dir, port, metrics, dashboard, policy=False)
    stack = start(cmd)
    try:
        wait_for(lambda: (run_dir / "checkpoints" / "dynamics-learner-0.pt").exists(), 180, "a learner checkpoint")
        services = {name: e["pid"] for name, e in table(run_dir)["processes"].items()}
        assert table(run_dir)["supervisor_pid"] == stack.pid
        killed_at = time.monotonic()
        stack.send_signal(signal.SIGKILL)
        stack.wait(30)
        wait_for(lambda: not any(pid_alive(p) for p in services.values()), 60, "every service to die with the supervisor")
        gone_s = time.monotonic() - killed_at
    finally:
        stop(stack, run_dir, timeout=30)
    again = start(cmd)
    try:
        wait_for(lambda: again.poll() is not None or table(run_dir).get("supervisor_pid") == again.pid, 90,
                 "the second supervisor's process table")
        assert again.poll() is None, again.communicate()[0]
        bus = Bus(f"tcp/127.0.0.1:{port}", run_dir, "run")
        resumed = wait_for(lambda: [b for b in bus.seen.of("dynamics-learner") if b.values.get("resumed_at_update", 0) > 0],
                           180, "the learner resumed from its checkpoint")[0]
        bus.close()
    finally:
        out = stop(again, run_dir)
    assert again.returncode == 0, out
    assert (run_dir / "summary.json").exists()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "supervisor.json").write_text(json.dumps(
        {"services_gone_s": round(gone_s, 1), "resumed_at_update": resumed.values["resumed_at_update"]}))
    print(f"services gone {gone_s:.1f} s after the supervisor's SIGKILL; resumed at update "
          f"{resumed.values['resumed_at_update']:.0f}")


def rss_mib(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(line for line in status.splitlines() if line.startswith("VmRSS")).split()[1]) // 1024


IN_FLIGHT_S = 10.0
"""A batch published this long before the learner's beat has reached it or is counted lost."""


def loss_accounts(seen) -> dict[str, int] | None:
    """The learner's newest beat against the worker's: what it received plus what it counted lost
    must lie between the worker's steps ``IN_FLIGHT_S`` before that beat (less the batch it was still
    filling) and its steps at or after it (what was published but still in flight). None until the
    worker beats after the learner's newest beat."""
    learner = seen.of("dynamics-learner")[-1]
    worker = seen.of("env-worker")
    earlier = [w for w in worker if w.timestamp <= learner.timestamp - IN_FLIGHT_S]
    later = [w for w in worker if w.timestamp >= learner.timestamp]
    if not earlier or not later:
        return None
    return {"published_before": int(earlier[-1].values["env_steps"]) - BATCH_STEPS,
            "received": int(learner.values["env_steps"]), "lost": int(learner.values["lost_steps"]),
            "lost_batches": int(learner.values["lost_batches"]),
            "published_after": int(later[0].values["env_steps"])}


def test_a_stalled_learner_stalls_nothing_else_and_its_memory_stays_bounded(tmp_path: Path) -> None:
    """The learner SIGSTOPped for 20 s under an unthrottled worker: the worker keeps stepping (its
    publications do not block on the stalled subscriber), the learner's memory does not grow with the
    backlog (its inbox is bounded; what overflows is dropped and counted), and it trains again at once."""
    run_dir, port, dashboard = tmp_path / "run", free_tcp_port(), free_tcp_port()
    metrics = 25000 + (os.getpid() % 1500) * 20
    cmd = command(run_dir, port, metrics, dashboard, policy=False)
    cmd[cmd.index("--worker-max-steps-per-second") + 1] = "0"
    stack = start(cmd)
    bus = None
    try:
        wait_for(lambda: "dynamics-learner" in table(run_dir).get("processes", {}), 90, "the learner started")
        bus = Bus(f"tcp/127.0.0.1:{port}", run_dir, "run")
        wait_for(lambda: bus.seen.reports, 240, "a graph report")
        pid = table(run_dir)["processes"]["dynamics-learner"]["pid"]
        steps, before = bus.seen.latest("env-worker", "env_steps"), rss_mib(pid)
        os.kill(pid, signal.SIGSTOP)
        stopped_at = time.time()
        try:
            wait_for(lambda: time.time() - stopped_at > 20 and bus.seen.latest("env-worker", "env_steps") > steps + 10_000,
                     60, "the worker stepping on while the learner is stopped")
            stepped = bus.seen.latest("env-worker", "env_steps") - steps
        finally:
            os.kill(pid, signal.SIGCONT)
        resumed_at = time.time()
        wait_for(lambda: bus.seen.rising("dynamics-learner", "updates", resumed_at), 120, "the learner training again")
        back_s = time.time() - resumed_at
        time.sleep(5)  # the backlog it was sent, drained
        after = rss_mib(pid)
        body = urllib.request.urlopen(f"http://127.0.0.1:{metrics + 1}/metrics", timeout=5).read().decode()
        drops = sum(float(line.rsplit(" ", 1)[1]) for line in body.splitlines()
                    if line.startswith('causeway_messages_dropped_total{reason="transitions_'))
        accounts = wait_for(lambda: loss_accounts(bus.seen), 60, "a worker beat after the learner's")
        assert table(run_dir)["processes"]["dynamics-learner"]["restarts"] == 0
        assert after - before < 150, (before, after)
        assert table(run_dir)["processes"]["env-worker-0"]["restarts"] == 0
        assert accounts["published_before"] <= accounts["received"] + accounts["lost"] <= accounts["published_after"], accounts
    finally:
        if bus is not None:
            bus.close()
        out = stop(stack, run_dir)
    assert stack.returncode == 0, out
    figures = {"stalled_s": 20, "worker_steps_meanwhile": int(stepped), "learner_rss_mib": [before, after],
               "learner_training_again_s": round(back_s, 1), "transitions_batches_dropped_counted": int(drops),
               "transitions": accounts}
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "stall.json").write_text(json.dumps(figures))
    print(json.dumps(figures))
