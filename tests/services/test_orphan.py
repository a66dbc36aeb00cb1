"""A service whose supervisor died ends (services/runtime/orphan.py): real processes, the parent SIGKILLed.

The child's loop either watches its stop flag (it stops at once, cleanly) or is stuck on a lock that
nothing will release (the watchdog ends it after its grace period), as an env-worker blocked in a bus
call was once seen to be after its supervisor, and the router in it, were killed."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

from services.runtime.orphan import ORPHAN_EXIT, PARENT_ENV, watch_parent
from tests import waiting

REPO = Path(__file__).resolve().parents[2]

CHILD = textwrap.dedent("""
    import sys, threading, time
    from services.runtime.orphan import watch_parent
    stopping = threading.Event()
    assert watch_parent(stopping, grace_s=1.0, interval_s=0.05, reaper_margin_s=1.0) is not None
    print("ready", flush=True)
    if sys.argv[1] == "gil":
        import ctypes
        ctypes.PyDLL(None).sleep(120)  # a native call that blocks holding the GIL: no thread runs
    elif sys.argv[1] == "stuck":
        lock = threading.Lock()
        lock.acquire()
        lock.acquire()  # never released: the loop never looks at its stop flag again
    else:
        while not stopping.is_set():
            time.sleep(0.05)
        with open(sys.argv[2], "w") as out:
            out.write("stopped cleanly")
""")

PARENT = textwrap.dedent("""
    import os, subprocess, sys
    env = {**os.environ, sys.argv[1]: str(os.getpid())}
    child = subprocess.Popen([sys.executable, "-c", sys.argv[2], sys.argv[3], sys.argv[4]], env=env,
                             stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "ready"
    print(child.pid, flush=True)
    import time
    time.sleep(600)
""")


def gone(pid: int) -> bool:
    """No such process, or only its zombie (reparented to an init that may not reap it)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True
    return "\nState:\tZ" in status


def orphan(mode: str, tmp_path: Path) -> tuple[int, float]:
    """Start parent -> child, SIGKILL the parent; the child's pid and the time of the kill."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT, PARENT_ENV, CHILD, mode, str(tmp_path / "out")],
                              cwd=REPO, stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        child = int(parent.stdout.readline())
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait()
    return child, time.monotonic()


def test_no_watchdog_without_a_supervisor() -> None:
    assert watch_parent(threading.Event(), environ={}) is None
    assert watch_parent(threading.Event(), environ={PARENT_ENV: "not a pid"}) is None


def test_a_loop_that_watches_its_stop_flag_stops_cleanly_when_the_supervisor_dies(tmp_path: Path) -> None:
    child, _ = orphan("clean", tmp_path)
    waiting.wait_for(lambda: gone(child), 20, "the orphaned child to exit")
    assert (tmp_path / "out").read_text() == "stopped cleanly"


def test_a_stuck_loop_is_ended_after_the_grace_period(tmp_path: Path) -> None:
    child, killed = orphan("stuck", tmp_path)
    waiting.wait_for(lambda: gone(child), 20, "the watchdog to end the stuck child")
    assert time.monotonic() - killed >= 0.9  # the grace period was given
    assert not (tmp_path / "out").exists()


def test_a_process_blocked_holding_the_gil_is_killed_by_the_reaper(tmp_path: Path) -> None:
    """No thread of it runs (the watchdog neither): the shell reaper outside it SIGKILLs it."""
    child, killed = orphan("gil", tmp_path)
    waiting.wait_for(lambda: gone(child), 20, "the reaper to kill the child blocked holding the GIL")
    assert time.monotonic() - killed >= 1.9  # the thread's grace and the reaper's margin were given
    assert not (tmp_path / "out").exists()


def test_the_watchdog_ends_with_the_orphan_status() -> None:
    """In-process: the parent pid is not ours, so the watchdog fires at once and calls ``exit``."""
    codes: list[int] = []
    stopping = threading.Event()
    thread = watch_parent(stopping, grace_s=0.05, interval_s=0.01, environ={PARENT_ENV: str(os.getppid() + 1)},
                          exit=codes.append, reaper_margin_s=None)
    assert thread is not None
    thread.join(5)
    assert stopping.is_set() and codes == [ORPHAN_EXIT]


def test_the_supervisor_names_itself_to_its_services(tmp_path: Path) -> None:
    from services.supervisor.processes import ManagedProcess

    proc = ManagedProcess("probe", "tests.services.print_env", {}, tmp_path / "probe.log")
    proc.start()
    proc.process.wait(30)
    assert f"{PARENT_ENV}={os.getpid()}" in (tmp_path / "probe.log").read_text()
