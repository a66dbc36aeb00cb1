"""Two "hosts" on one machine: network namespaces joined by a veth link, made and removed by the test.

Each host has its own loopback and one address on the link (10.231.0.1 and 10.231.0.2, /30). The
addresses exist only inside the two namespaces, so nothing the tests send leaves them. ``partition``
takes the link down (routes go with it; TCP connections across it stall, they are not reset) and
``heal`` brings it back. ``close`` ends every process started in the hosts, by pid, and deletes the
namespaces (the veth pair goes with them).

``make_host`` makes one namespace (loopback only) whose ``/etc/hosts`` names loopback as given
(``ip netns exec`` mounts ``/etc/netns/<namespace>/hosts`` over it): a name such as a Kubernetes
Service's ``router`` resolves there and nowhere else.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import pytest

SUBNET = "10.231.0.{}/30"


@dataclass
class Host:
    """One network namespace with an address on the link."""

    namespace: str
    link: str
    address: str
    processes: list[subprocess.Popen] = field(default_factory=list)

    def command(self, argv: Sequence[str]) -> list[str]:
        return ["ip", "netns", "exec", self.namespace, *argv]

    def start(self, argv: Sequence[str], env: dict[str, str] | None = None, cwd: Path | None = None,
              log: Path | None = None) -> subprocess.Popen:
        """A process in this host; its output to ``log`` (else a pipe), ended by ``close``."""
        out = open(log, "ab") if log else subprocess.PIPE
        process = subprocess.Popen(self.command(argv), env=env, cwd=cwd, stdout=out, stderr=subprocess.STDOUT
                                   if log else subprocess.PIPE, start_new_session=True)
        if log:
            out.close()
        self.processes.append(process)
        return process

    def run(self, argv: Sequence[str], timeout: float = 60, env: dict[str, str] | None = None,
            cwd: Path | None = None) -> subprocess.CompletedProcess:
        return subprocess.run(self.command(argv), env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)


@dataclass
class TwoHosts:
    a: Host
    b: Host

    def partition(self) -> None:
        _ip("-n", self.a.namespace, "link", "set", self.a.link, "down")

    def heal(self) -> None:
        _ip("-n", self.a.namespace, "link", "set", self.a.link, "up")

    def close(self) -> None:
        for host in (self.a, self.b):
            for process in host.processes:
                _end(process)
        for host in (self.a, self.b):
            subprocess.run(["ip", "netns", "delete", host.namespace], capture_output=True, timeout=30)


def _ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {result.stderr.strip()}")


def _end(process: subprocess.Popen) -> None:
    """SIGTERM to the process group the test started (``ip netns exec`` execs the program), then SIGKILL."""
    if process.poll() is not None:
        return
    try:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=10)
    except ProcessLookupError:
        pass


@dataclass
class OneHost:
    host: Host

    def close(self) -> None:
        for process in self.host.processes:
            _end(process)
        subprocess.run(["ip", "netns", "delete", self.host.namespace], capture_output=True, timeout=30)
        shutil.rmtree(Path("/etc/netns") / self.host.namespace, ignore_errors=True)


def make_host(tag: str, names: Sequence[str]) -> OneHost:
    """Namespace ``cw<tag>`` with loopback up, where each of ``names`` resolves to 127.0.0.1; skip where
    it cannot be made."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need root and iproute2")
    one = OneHost(Host(f"cw{tag}", "lo", "127.0.0.1"))
    try:
        etc = Path("/etc/netns") / one.host.namespace
        etc.mkdir(parents=True, exist_ok=True)
        (etc / "hosts").write_text("127.0.0.1 localhost " + " ".join(names) + "\n")
        _ip("netns", "add", one.host.namespace)
        _ip("-n", one.host.namespace, "link", "set", "lo", "up")
    except (RuntimeError, OSError) as exc:
        one.close()
        pytest.skip(f"cannot make a network namespace here: {exc}")
    return one


def make_two_hosts(tag: str) -> TwoHosts:
    """Namespaces ``cw<tag>a`` / ``cw<tag>b`` and their veth link; skip where they cannot be made."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need root and iproute2")
    a = Host(f"cw{tag}a", f"cw{tag}a"[:15], SUBNET.format(1).split("/")[0])
    b = Host(f"cw{tag}b", f"cw{tag}b"[:15], SUBNET.format(2).split("/")[0])
    hosts = TwoHosts(a, b)
    try:
        for host in (a, b):
            _ip("netns", "add", host.namespace)
        _ip("link", "add", a.link, "netns", a.namespace, "type", "veth", "peer", "name", b.link, "netns", b.namespace)
        for host, index in ((a, 1), (b, 2)):
            _ip("-n", host.namespace, "addr", "add", SUBNET.format(index), "dev", host.link)
            _ip("-n", host.namespace, "link", "set", "lo", "up")
            _ip("-n", host.namespace, "link", "set", host.link, "up")
    except RuntimeError as exc:
        hosts.close()
        pytest.skip(f"cannot make network namespaces here: {exc}")
    return hosts
