"""A private Docker engine for the compose smoke test (``make test-compose``).

Its own ``dockerd``, with data root, exec root, socket and pid file under one temporary directory,
so it shares nothing with any other engine on the machine; no iptables rules, no IP forwarding and
no default bridge, so a container reaches only the networks compose creates for the test (and
published ports on loopback). ``stop`` removes every container, stops the daemon by its pid, ends
the containerd shims it left by theirs, unmounts what it mounted and deletes the directory: the
machine is as before, also when a check failed.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

DOCKERD_FLAGS = ("--iptables=false", "--ip6tables=false", "--ip-forward=false", "--bridge=none",
                 "--storage-driver=overlay2", "--log-level=warn")
"""No NAT, no forwarding to other addresses, no shared ``docker0``: only the test's own networks."""


class EngineUnavailable(Exception):
    """No engine can start here (no dockerd, not root, or the daemon refused to start): skip, saying why."""


@dataclass
class Engine:
    """A running private dockerd."""

    root: Path
    process: subprocess.Popen
    log_path: Path

    @property
    def host(self) -> str:
        return f"unix://{self.root / 'docker.sock'}"

    def environ(self, **extra: str) -> dict[str, str]:
        """The environment for docker, docker-compose and the Docker SDK: this engine, the legacy builder."""
        env = {k: v for k, v in os.environ.items() if not k.startswith(("DOCKER_", "COMPOSE_"))}
        env.update(DOCKER_HOST=self.host, DOCKER_BUILDKIT="0", COMPOSE_DOCKER_CLI_BUILD="0", **extra)
        return env

    def docker(self, *args: str, timeout: float = 120, check: bool = True, input: bytes | None = None,
               stdout: int | None = subprocess.PIPE) -> subprocess.CompletedProcess:
        """``docker ARGS`` against this engine; raises with the output when ``check`` and it failed."""
        result = subprocess.run(["docker", *args], env=self.environ(), input=input, stdout=stdout,
                                stderr=subprocess.PIPE, timeout=timeout)
        if check and result.returncode != 0:
            raise RuntimeError(f"docker {' '.join(args)} failed ({result.returncode}): "
                               f"{result.stderr.decode(errors='replace')[-2000:]}")
        return result

    def log_tail(self, chars: int = 3000) -> str:
        return self.log_path.read_text(errors="replace")[-chars:] if self.log_path.exists() else ""


def start(timeout_s: float = 60.0) -> Engine:
    """Start a private dockerd; ``EngineUnavailable`` if that cannot be done here."""
    dockerd = shutil.which("dockerd")
    if dockerd is None or shutil.which("docker") is None:
        raise EngineUnavailable("dockerd/docker not installed (make sysdeps-compose installs docker.io)")
    if os.geteuid() != 0:
        raise EngineUnavailable("dockerd needs root here (no rootless engine set up)")
    root = Path(tempfile.mkdtemp(prefix="causeway-dockerd-"))
    log_path = root / "dockerd.log"
    command = [dockerd, *DOCKERD_FLAGS, f"--data-root={root / 'data'}", f"--exec-root={root / 'exec'}",
               f"--pidfile={root / 'dockerd.pid'}", f"--host=unix://{root / 'docker.sock'}"]
    with open(log_path, "wb") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    engine = Engine(root, process, log_path)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            tail = engine.log_tail()
            _cleanup(engine)
            raise EngineUnavailable(f"dockerd exited with {process.returncode}: {tail}")
        if engine.docker("version", "--format", "{{.Server.Version}}", check=False, timeout=10).returncode == 0:
            return engine
        time.sleep(0.25)
    stop(engine)
    raise EngineUnavailable(f"dockerd did not answer within {timeout_s:.0f} s: {engine.log_tail()}")


def stop(engine: Engine) -> None:
    """Remove every container, stop dockerd by its pid and leave nothing of it behind."""
    if engine.process.poll() is None:
        ids = engine.docker("ps", "-aq", check=False, timeout=30).stdout.decode().split()
        if ids:
            engine.docker("rm", "-f", "-v", *ids, check=False, timeout=120)
        engine.process.send_signal(signal.SIGTERM)
        try:
            engine.process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            engine.process.kill()
            engine.process.wait(timeout=30)
    _cleanup(engine)


def _cleanup(engine: Engine) -> None:
    for pid in _processes_under(engine.root):
        _kill(pid)
    for mount in sorted(_mounts_under(engine.root), key=len, reverse=True):
        subprocess.run(["umount", "-l", mount], capture_output=True, timeout=30)
    # rm, not shutil.rmtree: the image layers are ~10 GB in many small files (minutes either way);
    # --one-file-system: never into something still mounted.
    subprocess.run(["rm", "-rf", "--one-file-system", str(engine.root)], capture_output=True, timeout=1800)
    shutil.rmtree(engine.root, ignore_errors=True)


def _processes_under(root: Path) -> list[int]:
    """Pids of processes (containerd shims, docker-proxy) whose command line names ``root``."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(root) in cmdline:
            found.append(int(entry.name))
    return found


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _mounts_under(root: Path) -> list[str]:
    """Mount points below ``root`` (``<exec-root>/netns/default``, overlay and shm mounts)."""
    points = []
    for line in Path("/proc/self/mounts").read_text().splitlines():
        fields = line.split()
        if len(fields) > 1 and fields[1].startswith(str(root)):
            points.append(fields[1].encode().decode("unicode_escape"))
    return points


def run_logged(command: Sequence[str], log: Path, timeout: float, env: dict[str, str] | None = None,
               cwd: Path | None = None) -> float:
    """Run ``command`` with its output appended to ``log``; its wall time in seconds, or raise with the tail."""
    started = time.monotonic()
    with open(log, "ab") as out:
        out.write(f"\n$ {' '.join(command)}\n".encode())
        out.flush()
        result = subprocess.run(list(command), stdout=out, stderr=subprocess.STDOUT, env=env, cwd=cwd,
                                timeout=timeout)
    if result.returncode != 0:
        raise RuntimeError(f"{command[0]} failed ({result.returncode}); log {log}:\n"
                           f"{log.read_text(errors='replace')[-3000:]}")
    return time.monotonic() - started
