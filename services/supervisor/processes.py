"""Service processes: spawn, watch, restart with back-off, stop politely, then firmly."""
from __future__ import annotations

import ctypes
import json
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from services.runtime.checkpoint import CONFIG_ERROR_EXIT
from services.runtime.orphan import PARENT_ENV

log = logging.getLogger("supervisor")
PR_SET_PDEATHSIG = 1


class FatalServiceError(RuntimeError):
    """A service that restarting will not fix: the run stops and says why."""


@dataclass
class ManagedProcess:
    """One service instance as an OS process (``python -m <module>``) with its environment."""

    name: str
    module: str
    environ: dict[str, str]
    log_path: Path
    restarts: int = 0
    max_restarts: int = 20
    process: subprocess.Popen | None = None
    next_start: float = 0.0
    exit_codes: list[int] = field(default_factory=list)
    refresh: Callable[[], dict[str, str]] | None = None
    """Environment read afresh at each (re)start, over ``environ`` (the versions known published then)."""

    def start(self) -> None:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, **self.environ, **(self.refresh() if self.refresh else {}), "PYTHONUNBUFFERED": "1",
               PARENT_ENV: str(os.getpid())}
        with open(self.log_path, "ab") as out:
            self.process = subprocess.Popen([sys.executable, "-m", self.module], env=env, stdout=out,
                                            stderr=subprocess.STDOUT, start_new_session=True,
                                            preexec_fn=_die_with_parent)
        log.info("started %s (pid %d)", self.name, self.process.pid)

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process else None

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def check(self, now: float) -> bool:
        """Restart a crashed process after a back-off; returns True when it (re)started now."""
        if self.process is None or self.alive():
            return False
        if self.next_start == 0.0:
            code = self.process.returncode
            self.exit_codes.append(code)
            if code == CONFIG_ERROR_EXIT:
                raise FatalServiceError(f"{self.name} stopped for a configuration reason: "
                                        f"{self.last_error() or 'see its log'} ({self.log_path})")
            if self.restarts >= self.max_restarts:
                raise FatalServiceError(f"{self.name} crashed {self.restarts + 1} times; last exit code {code}; see {self.log_path}")
            self.next_start = now + min(0.5 * 2 ** self.restarts, 10.0)
            log.warning("%s exited with %s; restarting", self.name, code)
        if now >= self.next_start:
            self.restarts += 1
            self.next_start = 0.0
            self.start()
            return True
        return False

    def last_error(self) -> str:
        """The last ERROR line of the process's log (its reason for a configuration exit), or ''."""
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()[-200:]
        except OSError:
            return ""
        errors = [line for line in lines if " ERROR " in line or ": error: " in line]
        return errors[-1].split(": ", 1)[-1].strip() if errors else ""

    def terminate(self) -> None:
        if self.alive():
            self.process.send_signal(signal.SIGTERM)

    def wait(self, timeout: float) -> None:
        if self.process is None:
            return
        try:
            self.process.wait(timeout=max(timeout, 0.01))
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop in time; killing", self.name)
            self.process.kill()
            self.process.wait()


def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM when the supervisor dies (Linux ``PR_SET_PDEATHSIG``), so a
    killed supervisor leaves no service running (each checkpoints and exits on SIGTERM)."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def leftovers(run_dir: Path) -> list[str]:
    """Processes a previous supervisor of ``run_dir`` started that still run (from its processes.json):
    ``"<what> (pid N)"``. A second run on the same directory must not start beside them."""
    try:
        table = json.loads((run_dir / "processes.json").read_text())
    except (OSError, ValueError):
        return []
    found = []
    candidates = [("supervisor", table.get("supervisor_pid"), "services.cli")] + [
        (name, entry.get("pid"), entry.get("module", "")) for name, entry in table.get("processes", {}).items()]
    for name, pid, module in candidates:
        if isinstance(pid, int) and pid != os.getpid() and module and module in _cmdline(pid):
            found.append(f"{name} (pid {pid})")
    return found


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def stop_all(processes: list[ManagedProcess], timeout: float = 30.0) -> None:
    """SIGTERM everyone (they checkpoint and exit), then SIGKILL whoever is still there."""
    for p in processes:
        p.terminate()
    deadline = time.monotonic() + timeout
    for p in processes:
        p.wait(deadline - time.monotonic())
