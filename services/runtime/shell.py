"""The thin layer every service.py shares: bus session, liveliness, metrics, control, inboxes, beats.

Cores never import this module. A service's ``run(cfg)`` builds a ``ServiceShell``, wires its core
to inboxes and publishers, and loops until ``shell.stopping``.
"""
from __future__ import annotations

import logging
import signal
import sys
import threading
from collections import deque
import time
from pathlib import Path
from typing import Any, Callable

from proto import topics
from proto.codec import ProtocolError, decode, encode
from proto.messages import Control, EnvSpec, ServiceStats
from services.bus.base import Transport
from services.runtime.checkpoint import CONFIG_ERROR_EXIT, CheckpointMismatch
from services.runtime.config import ServiceConfig, parse_config, write_config
from services.runtime.metrics import ServiceMetrics
from services.runtime.orphan import watch_parent

log = logging.getLogger(__name__)
DEFAULT_INBOX_BYTES = 256 * 2**20
"""Payload bytes an inbox holds at most (a message may be 64 MiB; a queue of 256 of them would be 16 GiB)."""


class Inbox:
    """A bounded queue of validated messages from one subscription.

    Invalid payloads are counted in ``causeway_messages_rejected_total{reason}`` and dropped. The
    queue is bounded in messages (``maxsize``) and in payload bytes (``max_bytes``): past either, the
    oldest messages are dropped and counted (``{name}_queue_full``, ``{name}_bytes_full``), so a slow
    consumer never blocks the bus and never holds more than ``max_bytes`` of messages.
    """

    def __init__(self, name: str, expected: type | tuple[type, ...], maxsize: int, metrics: ServiceMetrics,
                 max_bytes: int = DEFAULT_INBOX_BYTES) -> None:
        self.name, self.expected, self.metrics = name, expected, metrics
        self.maxsize, self.max_bytes = maxsize, max_bytes
        self.items: deque[tuple[str, Any, int]] = deque()
        self.bytes = 0
        self.ready = threading.Condition()

    def on_payload(self, key: str, payload: bytes) -> None:
        try:
            message = decode(payload, self.expected)
            check_worker_key(key, message)
        except ProtocolError as exc:
            self.metrics.reject(exc.reason)
            log.warning("rejected message on %s: %s", key, exc)
            return
        self.metrics.received.labels(type=type(message).TYPE).inc()
        with self.ready:
            while self.items and (len(self.items) >= self.maxsize or self.bytes + len(payload) > self.max_bytes):
                reason = "queue_full" if len(self.items) >= self.maxsize else "bytes_full"
                self.bytes -= self.items.popleft()[2]
                self.metrics.dropped.labels(reason=f"{self.name}_{reason}").inc()
            self.items.append((key, message, len(payload)))
            self.bytes += len(payload)
            self.ready.notify()
        self.metrics.queue_depth.labels(queue=self.name).set(len(self.items))

    def _pop(self) -> tuple[str, Any]:
        key, message, size = self.items.popleft()
        self.bytes -= size
        return key, message

    def drain(self, limit: int = 1_000_000) -> list[tuple[str, Any]]:
        with self.ready:
            items = [self._pop() for _ in range(min(limit, len(self.items)))]
        self.metrics.queue_depth.labels(queue=self.name).set(len(self.items))
        return items

    def get(self, timeout: float) -> tuple[str, Any] | None:
        with self.ready:
            if not self.items and not self.ready.wait_for(lambda: bool(self.items), timeout):
                return None
            return self._pop()


def check_worker_key(key: str, message: Any) -> None:
    """``ProtocolError('inconsistent')`` for a worker's message (transitions, frames, skills, scored,
    induced graphs) whose ``worker_id`` is not its key's last segment. The router pins each env-worker to
    its own keys (``services.bus.roles.pinned``); this pins what the message says to the key, so worker 0
    cannot send batches that call themselves worker 1's on its own key."""
    inner = getattr(message, "transitions", message)
    worker = getattr(inner, "worker_id", None)
    if isinstance(worker, str) and key.rsplit("/", 1)[-1] != worker:
        raise ProtocolError("inconsistent", f"a message of worker {worker!r} on {key}")


class ServiceShell:
    """Bus session, liveliness token, /metrics, control commands and progress beats of one service."""

    def __init__(self, service: str, cfg: ServiceConfig, transport: Transport | None = None) -> None:
        self.service, self.cfg = service, cfg
        if transport is None:
            transport = open_zenoh(cfg)
        self.transport = transport
        self.metrics = ServiceMetrics(service, cfg.instance)
        self.metrics.serve(cfg.metrics_port, cfg.metrics_host)
        self.stopping = threading.Event()
        self.paused = False
        self.checkpoint_requested = False
        self._handles: list[Any] = []
        self._last_beat = 0.0
        self._control = self.inbox("control", Control, maxsize=64)
        for target in (service, "all"):
            self._handles.append(transport.subscribe(topics.control(cfg.run_id, target), self._control.on_payload))
        self._handles.append(transport.declare_token(topics.alive(cfg.run_id, service, cfg.instance)))
        if threading.current_thread() is threading.main_thread():
            self.install_signal_handlers()
            watch_parent(self.stopping)
        log.info("%s %s started (run %s, bus %s)", service, cfg.instance, cfg.run_id, cfg.zenoh_connect)

    def install_signal_handlers(self) -> None:
        """SIGTERM/SIGINT ask the loop to stop cleanly (checkpoint, then exit); done automatically
        when the shell is built on the main thread (a service process), not in in-process threads."""
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: self.stopping.set())

    def inbox(self, name: str, expected: type | tuple[type, ...], maxsize: int) -> Inbox:
        return Inbox(name, expected, maxsize, self.metrics)

    def subscribe(self, key_expr: str, inbox: Inbox) -> None:
        self._handles.append(self.transport.subscribe(key_expr, inbox.on_payload))

    def publish(self, key: str, message: Any, reliable: bool = True) -> int:
        payload = encode(message)
        self.transport.publish(key, payload, reliable=reliable)
        return len(payload)

    @property
    def checkpoint_path(self) -> Path:
        return Path(self.cfg.run_dir) / "checkpoints" / f"{self.service}-{self.cfg.instance}.pt"

    def write_effective_config(self) -> None:
        """The service's effective configuration into <run_dir>/config/<service>-<instance>.json."""
        write_config(self.cfg, Path(self.cfg.run_dir) / "config" / f"{self.service}-{self.cfg.instance}.json")

    def resume(self, core: Any) -> Path:
        """Write the effective config and restore ``core`` from this service's checkpoint, if any.

        A checkpoint made for another environment or model is a configuration error, not a crash:
        the process exits with CONFIG_ERROR_EXIT, which the supervisor does not restart."""
        self.write_effective_config()
        path = self.checkpoint_path
        try:
            if core.restore(path):
                log.info("%s resumed from %s", self.service, path)
        except CheckpointMismatch as exc:
            log.error("%s", exc)
            self.close()
            sys.exit(CONFIG_ERROR_EXIT)
        return path

    def checkpoint_if_due(self, core: Any, path: Path, last: float, written: Any = None) -> float:
        """Checkpoint ``core`` to ``path`` when a ``checkpoint`` command asked for it or ``checkpoint_every_s``
        has passed since ``last`` (a ``time.monotonic()``); counts it on ``written`` (a Counter) if given.
        Returns the time of the last checkpoint, to pass back next time."""
        now = time.monotonic()
        if not (self.checkpoint_requested or now - last >= self.cfg.checkpoint_every_s):
            return last
        core.checkpoint(path)
        if written is not None:
            written.inc()
        self.checkpoint_requested = False
        return now

    def guarded(self, apply: Callable[[Any], Any], message: Any) -> Any:
        """``apply(message)``; a ProtocolError (the message does not fit this run) is counted and dropped."""
        try:
            return apply(message)
        except ProtocolError as exc:
            self.metrics.reject(exc.reason)
            log.warning("rejected %s: %s", type(message).__name__, exc)
            return None

    def set_latest(self, latest: Any, message: Any) -> int:
        """Encode ``message`` into a ``serve_latest`` value (which also publishes it); returns its size."""
        payload = encode(message)
        latest.set(payload)
        return len(payload)

    def poll_control(self) -> None:
        """Apply pending control commands to the shell's flags."""
        for _, command in self._control.drain():
            log.info("control: %s %s", command.command, command.argument)
            if command.command == "stop":
                self.stopping.set()
            elif command.command == "pause":
                self.paused = True
            elif command.command == "resume":
                self.paused = False
            elif command.command == "checkpoint":
                self.checkpoint_requested = True

    def wait_for_spec(self, poll_s: float = 0.5, key: str | None = None) -> EnvSpec | None:
        """Query the EnvSpec on ``key`` (default: the env-workers' ``env/spec``) until one answers (None if
        stopped first). Control commands are applied while it waits: a run stopped before any spec came
        (a frames run stopped before its slots froze) must not leave the service querying forever."""
        while True:
            self.poll_control()
            if self.stopping.is_set():
                return None
            for spec in self.query(key or topics.env_spec(self.cfg.run_id), EnvSpec, timeout=poll_s):
                return spec
            self.stopping.wait(poll_s)

    def query(self, key: str, expected: type, timeout: float = 1.0) -> list[Any]:
        """The decoded answers of a query on ``key``; an answer off the contract is counted and dropped."""
        found = []
        for source, payload in self.transport.query(key, timeout=timeout):
            try:
                found.append(decode(payload, expected))
            except ProtocolError as exc:
                self.metrics.reject(exc.reason)
                log.warning("rejected %s from %s: %s", expected.__name__, source, exc)
        return found

    def beat(self, values: dict[str, float], force: bool = False) -> None:
        """Publish a ServiceStats progress beat, at most every ``stats_interval_s``."""
        now = time.time()
        if not force and now - self._last_beat < self.cfg.stats_interval_s:
            return
        self._last_beat = now
        stats = ServiceStats(service=self.service, instance=self.cfg.instance,
                             values={**{k: float(v) for k, v in values.items()},
                                     "messages_rejected": float(self.metrics.rejected_count)}, timestamp=now)
        self.publish(topics.stats(self.cfg.run_id, self.service, self.cfg.instance), stats, reliable=False)

    def close(self) -> None:
        for handle in reversed(self._handles):
            try:
                handle.close()
            except Exception:  # closing must go on for the rest
                log.exception("closing a bus handle failed")
        self.transport.close()


def open_zenoh(cfg: ServiceConfig) -> Transport:
    """A Zenoh client of ``cfg.zenoh_connect``, as the user of ``cfg.bus_credentials`` when set; an
    unreadable credentials file is a configuration error (``CONFIG_ERROR_EXIT``: not restarted)."""
    from services.bus.credentials import read_credentials
    from services.bus.zenoh_transport import ZenohTransport

    credentials = None
    if cfg.bus_credentials:
        try:
            credentials = read_credentials(cfg.bus_credentials)
        except ValueError as exc:
            log.error("%s", exc)
            sys.exit(CONFIG_ERROR_EXIT)
    return ZenohTransport(cfg.zenoh_connect, credentials, cfg.bus_tls_root_ca)


def setup_logging(service: str) -> None:
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s {service} %(levelname)s %(name)s: %(message)s")


def service_main(service: str, config_cls: type, run: Callable[[Any], None], argv: list[str] | None,
                 models: bool = False) -> None:
    """The entry point of every service process: logging, one torch thread, config from env and flags.

    A service that trains or evaluates the method's ``models`` checks ``--device`` first: ``cuda``
    where there is none exits with ``CONFIG_ERROR_EXIT`` before the bus is opened."""
    setup_logging(service)
    import torch
    torch.set_num_threads(1)
    cfg = parse_service_config(config_cls, argv)
    if models:
        check_device(service, cfg)
    run(cfg)


def check_device(service: str, cfg: Any) -> None:
    """Exit with ``CONFIG_ERROR_EXIT`` if ``cfg.device`` cannot be used here by ``cfg.method``."""
    from causal.methods import get_method
    from services.runtime.device import resolve_device

    try:
        device = resolve_device(cfg.device, get_method(cfg.method).devices)
    except ValueError as exc:
        log.error("%s: %s", service, exc)
        sys.exit(CONFIG_ERROR_EXIT)
    log.info("%s runs its models on %s (--device %s)", service, device, cfg.device)


def parse_service_config(config_cls: type, argv: list[str] | None) -> Any:
    """A service's configuration; a refused one exits with ``CONFIG_ERROR_EXIT`` (the supervisor then
    stops the run with the reason instead of restarting the service)."""
    try:
        return parse_config(config_cls, argv)
    except SystemExit as exc:
        if exc.code not in (0, None):
            sys.exit(CONFIG_ERROR_EXIT)
        raise
