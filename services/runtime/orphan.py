"""A service whose supervisor died must not run on (issue 20 item 6).

The supervisor starts each service with ``PR_SET_PDEATHSIG`` (SIGTERM when it dies), and SIGTERM asks
the service's loop to stop: it checkpoints and exits. That is not enough on its own: the Zenoh router
lives in the supervisor's process, and a loop blocked in a bus call or on a lock that call holds never
gets back to look at its stop flag (seen once: an env-worker acting with a PPO policy ran on for over
90 s after its supervisor was SIGKILLed, SIGTERM caught, loop stuck). So a watchdog thread, which needs
neither the main thread nor the bus, sees the parent go, asks the loop to stop as SIGTERM does, and if
the process is still there ``grace_s`` later ends it with :func:`os._exit`. A thread still needs the
GIL, and a native call that blocks while holding it (seen: a policy-learner still running 60 s after
its supervisor's SIGKILL, with this thread in place) stops every thread; so a reaper outside the
interpreter, a small shell loop started beside the service, SIGKILLs it ``REAPER_MARGIN_S`` after the
thread's deadline if it is still there.

Only processes a local supervisor started are watched (it names itself in :data:`PARENT_ENV`); compose
and Kubernetes services have no such parent (the container runtime stops them).
"""
from __future__ import annotations

import logging
import math
import os
import subprocess
import threading
import time
from typing import Callable

PARENT_ENV = "CAUSEWAY_SUPERVISOR_PID"
"""The pid of the supervisor that started this process (set by ``services.supervisor.processes``)."""
GRACE_S = 30.0
"""How long a service whose supervisor is gone may take to checkpoint and exit before it is ended."""
ORPHAN_EXIT = 143
"""Exit status of a process ended by the watchdog (as if by SIGTERM: 128 + 15)."""
REAPER_MARGIN_S = 5.0
"""How long after the thread's deadline the reaper SIGKILLs a process the thread could not end."""
REAPER = r"""
svc=$1 sup=$2 grace=$3
started() { sed 's/.*) //' /proc/$svc/stat 2>/dev/null | cut -d' ' -f20; }
start=$(started)
while [ -e /proc/$svc ]; do
  ppid=$(sed -n 's/^PPid:[[:space:]]*//p' /proc/$svc/status 2>/dev/null)
  if [ -n "$ppid" ] && [ "$ppid" != "$sup" ]; then
    i=0
    while [ "$i" -lt "$grace" ]; do
      sleep 1
      i=$((i + 1))
      [ "$(started)" = "$start" ] || exit 0
    done
    kill -9 "$svc" 2>/dev/null
    exit 0
  fi
  sleep 1
done
"""
"""The reaper (``sh -c REAPER reaper <service pid> <supervisor pid> <whole seconds>``): while the service
runs, watch its parent in /proc (reparenting happens when the supervisor exits, zombie or not); once it
is another, wait the seconds and SIGKILL the service, unless it is gone by then (its start time in
/proc/<pid>/stat no longer the one it had, so a reused pid is never killed). Ends by itself with the
service."""

log = logging.getLogger("orphan")


def watch_parent(stopping: threading.Event, grace_s: float = GRACE_S, interval_s: float = 0.5,
                 environ: dict[str, str] | None = None, exit: Callable[[int], None] = os._exit,
                 reaper_margin_s: float | None = REAPER_MARGIN_S) -> threading.Thread | None:
    """Start the watchdog (a daemon thread, and the reaper unless ``reaper_margin_s`` is None) if a
    supervisor started this process, else None."""
    value = (os.environ if environ is None else environ).get(PARENT_ENV, "")
    if not value.isdigit():
        return None
    thread = threading.Thread(target=_watch, args=(int(value), stopping, grace_s, interval_s, exit),
                              name="orphan-watchdog", daemon=True)
    thread.start()
    if reaper_margin_s is not None and os.path.isdir(f"/proc/{os.getpid()}"):
        seconds = str(math.ceil(grace_s + reaper_margin_s))
        subprocess.Popen(["/bin/sh", "-c", REAPER, "reaper", str(os.getpid()), value, seconds],
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         close_fds=True)
    return thread


def _watch(parent: int, stopping: threading.Event, grace_s: float, interval_s: float,
           exit: Callable[[int], None]) -> None:
    while os.getppid() == parent:
        time.sleep(interval_s)
    log.error("the supervisor (pid %d) is gone: stopping, and ending this process in %.0f s if it has not "
              "stopped by then", parent, grace_s)
    stopping.set()
    time.sleep(grace_s)
    log.error("still running %.0f s after the supervisor died: ending it", grace_s)
    logging.shutdown()
    exit(ORPHAN_EXIT)
