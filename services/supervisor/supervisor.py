"""``causeway run``: the embedded default stack.

A Zenoh router runs inside this process (a Python session in router mode on 127.0.0.1, multicast
scouting off); every service runs as its own OS process connected to it. The supervisor restarts
crashed services (they resume from their checkpoints), shows live progress from the services' stats
beats and graph reports, stops on a target, a time or a step budget, and writes the run directory.

The parts, each readable on its own: what runs and what each service is told
(:mod:`services.supervisor.wiring`), process supervision (:mod:`services.supervisor.processes`),
when the run stops (:mod:`services.supervisor.stop_rules`), and what the run leaves behind
(:mod:`services.supervisor.analysis`). This module holds them together around the bus.
"""
from __future__ import annotations

import json
import logging
import os
import queue
import signal
import threading
import time
from pathlib import Path

from causal.methods import get_method
from envs.registry import env_entry
from proto import topics
from proto.codec import ProtocolError, decode, encode
from proto.messages import Control, GraphReport, LocalGraphReport, ServiceStats
from services.bus.credentials import read_credentials
from services.bus.router import start_router, wait_for_router
from services.bus.zenoh_transport import ZenohTransport
from services.dynamics_learner.core import DynamicsLearnerCore
from services.runtime.accept import VersionGate
from services.runtime.config import to_environ, write_config
from services.runtime.device import resolve_device
from services.supervisor.analysis import RunRecord, analyse, git_revision
from services.supervisor.config import RunConfig
from services.supervisor.processes import FatalServiceError, ManagedProcess, leftovers, stop_all
from services.supervisor.progress import Progress
from services.runtime.live_scores import live_row
from services.supervisor.report_skills import skill_facts
from services.supervisor.report_slots import label_facts, slot_facts
from services.supervisor.stop_rules import StopRules
from services.supervisor.wiring import (MODULES, check_ports_free, credentials_path, learning_services,
                                       prepare_bus_auth, resolve, scores_local_graphs, service_configs,
                                       worker_config)

log = logging.getLogger("supervisor")
KNOWN_VERSION_ENV = "CAUSEWAY_KNOWN_VERSION"
"""The environment variable of every service's ``known_version`` (``services.runtime.config``)."""


class Supervisor:
    """Owns the router, the service processes and the run directory of one local run."""

    def __init__(self, cfg: RunConfig) -> None:
        self.cfg = resolve(cfg)
        self.run_dir = Path(self.cfg.run_dir)
        self.connect = f"tcp/127.0.0.1:{self.cfg.router_port}"
        self.processes: dict[str, ManagedProcess] = {}
        self.progress = Progress(interactive=None if self.cfg.progress else False,
                                 every_s=10.0 if self.cfg.progress else 1e9,
                                 global_graph=get_method(self.cfg.method).global_graph is not None,
                                 local_graphs=scores_local_graphs(self.cfg))
        self.history: list[dict[str, float]] = []
        self.last_report: GraphReport | None = None
        self.revision: str | None = None  # the commit that runs, read once at the start
        self.last_local: LocalGraphReport | None = None
        self.local_history: list[dict[str, float]] = []
        self.live_history: list[dict[str, float]] = []
        """The learner's live scores (``live_*`` in its beats) each time they change: summary ``live_history``."""
        self.stop_reason = ""
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.report_versions = VersionGate()
        self.started: set[str] = set()
        """Names of every process this supervisor started (retired workers too)."""
        self.strangers: set[tuple[str, str]] = set()
        """Report versions taken into the history: each newer than the last, by a bounded step."""
        self._own_stop = -1.0
        self.pending_scale: queue.Queue[str] = queue.Queue()
        self.retired: list[ManagedProcess] = []
        self.failure = ""
        self.policy_timeline: list[tuple[float, str, str, float]] = []
        """(seconds since start, service, instance, policy version) whenever a version changes."""
        self.stop_rules = StopRules(self.cfg, self._pause_workers)

    @property
    def dashboard_url(self) -> str | None:
        port = self.cfg.dashboard_port
        return f"http://127.0.0.1:{port}/?run={self.cfg.run_id}" if port else None

    def process(self, name: str, module: str, service_cfg: object) -> ManagedProcess:
        policy = module == MODULES["env-worker"]
        proc = ManagedProcess(name, module, to_environ(service_cfg), self.run_dir / "logs" / f"{name}.log",
                              refresh=lambda: {KNOWN_VERSION_ENV: str(self.known_version(policy))})
        self.processes[name] = proc
        self.started.add(name)
        return proc

    def started_it(self, stats: ServiceStats, key: str) -> bool:
        """Whether ``stats`` names a process this supervisor started (env-worker i is instance i, every
        other service instance 0), under that process's own key (``stats/<service>/<instance>``): only
        those count in the run's progress and budgets. With ``--bus-auth`` the router lets only that
        process's user publish on its key (:func:`services.bus.roles.pinned`), so a beat that counts is
        the process's own; a beat naming another process than its key is refused here."""
        if key.split("/")[-2:] != [stats.service, stats.instance]:
            return False
        if stats.service == "env-worker":
            return f"env-worker-{stats.instance}" in self.started
        return stats.service in self.started and stats.instance == "0"

    def published_version(self) -> int:
        """The dynamics-learner's record of the weights versions it published (0 before any): it writes
        it before each publication (``DynamicsLearnerCore.record_version``), on disk, where nothing on the
        bus can forge it. No report can be about a version above it."""
        path = DynamicsLearnerCore.version_path(self.run_dir / "checkpoints" / "dynamics-learner-0.pt")
        try:
            return max(int(json.loads(path.read_text())["version"]), 0)
        except (OSError, ValueError, KeyError, TypeError):
            return 0

    def known_version(self, policy: bool) -> int:
        """The version a process started now is told is known published (``known_version``, which bounds the
        first version it takes): for an env-worker, the newest policy version the policy-learner's beats
        gave; for every other service, :meth:`published_version`."""
        if not policy:
            return self.published_version()
        beat = self.progress.stats.get(("policy-learner", "0"))
        return max(int(beat.values.get("policy_version", 0)), 0) if beat is not None else 0

    def preflight(self) -> None:
        """``ValueError`` if the run cannot start here: ``--device cuda`` without a CUDA device (or with a
        method that runs on the CPU only), a port it needs is taken, or processes of an earlier
        supervisor of this run directory still run."""
        resolve_device(self.cfg.device, get_method(self.cfg.method).devices)
        running = leftovers(self.run_dir)
        if running:
            raise ValueError(f"{self.run_dir} is in use: {', '.join(running)} still run; stop them "
                             f"(causeway stop --run-dir {self.run_dir}, or kill the pids) or use another --run-dir")
        check_ports_free(self.cfg)

    def start(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._write_run_config()
        auth = prepare_bus_auth(self.cfg)
        self.router = start_router(f"tcp/127.0.0.1:{self.cfg.router_port}", auth)
        own = read_credentials(credentials_path(self.cfg, "supervisor")) if auth else None
        wait_for_router(self.connect, credentials=own)
        self.bus = ZenohTransport(self.connect, own)
        self.bus.subscribe(topics.stats(self.cfg.run_id), self._on_stats)
        self.bus.subscribe(topics.graph(self.cfg.run_id), self._on_graph)
        self.bus.subscribe(topics.local(self.cfg.run_id), self._on_local)
        for target in ("supervisor", "all"):
            self.bus.subscribe(topics.control(self.cfg.run_id, target), self._on_control)
        self.bus.declare_token(topics.alive(self.cfg.run_id, "supervisor", "0"))
        configs = service_configs(self.cfg, self.connect)
        for name in learning_services(self.cfg) + (("dashboard",) if self.cfg.dashboard_port else ()):
            self.process(name, MODULES[name], configs[name]).start()
        for i in range(self.cfg.workers):
            self.add_worker(i)
        self._write_process_table()

    def _write_process_table(self) -> None:
        """<run_dir>/processes.json: pid, restarts and log of every service process (for operators)."""
        table = {name: {"pid": p.pid, "module": p.module, "restarts": p.restarts, "log": str(p.log_path)}
                 for name, p in self.processes.items()}
        tmp = self.run_dir / "processes.json.tmp"
        tmp.write_text(json.dumps({"router": self.connect, "supervisor_pid": os.getpid(), "processes": table}, indent=1))
        tmp.replace(self.run_dir / "processes.json")

    def add_worker(self, index: int) -> None:
        self.process(f"env-worker-{index}", MODULES["env-worker"], worker_config(self.cfg, self.connect, index)).start()

    def worker_indices(self) -> list[int]:
        return sorted(int(name.rsplit("-", 1)[1]) for name in self.processes if name.startswith("env-worker-"))

    def free_worker_index(self) -> int | None:
        """The lowest worker index below ``--max-workers`` that no running or still-stopping worker holds
        (None if every one is held). Indices are bus identities drawn before the router started
        (:func:`~services.supervisor.wiring.prepare_bus_auth`), so a new worker reuses a retired one's;
        its seeds still differ, since each start of an index is a new life (``next_generation``)."""
        self.retired = [proc for proc in self.retired if proc.alive()]
        held = set(self.worker_indices()) | {int(proc.name.rsplit("-", 1)[1]) for proc in self.retired}
        return next((i for i in range(self.cfg.max_workers) if i not in held), None)

    def scale_workers(self, count: int) -> None:
        """Add workers (free indices below ``--max-workers``, new lives so new seeds) or retire the newest
        ones; nothing else restarts.

        A retired worker gets SIGTERM, finishes and publishes the batch it is collecting, and exits; until
        it has, its index (its bus identity) is not given to a new worker."""
        if count < 0:
            raise ValueError(f"cannot scale env-worker to {count}")
        current = self.worker_indices()
        for _ in range(count - len(current)):
            index = self.free_worker_index()
            if index is None:
                log.warning("env-worker: every index below --max-workers %d is held (retired workers still "
                            "stopping); scale again once they have exited", self.cfg.max_workers)
                break
            self.add_worker(index)
        for index in sorted(current, reverse=True)[: max(len(current) - count, 0)]:
            proc = self.processes.pop(f"env-worker-{index}")
            proc.terminate()
            self.retired.append(proc)
        self._write_process_table()
        log.warning("env-worker scaled from %d to %d", len(current), len(self.worker_indices()))

    def _on_control(self, key: str, payload: bytes) -> None:
        try:
            command = decode(payload, Control)
        except ProtocolError:
            log.warning("bad control message on %s", key)
            return
        if command.command == "stop" and command.issued_at != self._own_stop:
            self.request_stop("stopped by an operator")
        elif command.command == "scale":
            self.pending_scale.put(command.argument)

    def _apply_scale_requests(self) -> None:
        while not self.pending_scale.empty():
            argument = self.pending_scale.get_nowait()
            service, _, count = argument.partition("=")
            if service != "env-worker" or not count.isdigit() or int(count) > self.cfg.max_workers:
                log.warning("ignored scale request %r (expected env-worker=N, N <= --max-workers %d)", argument,
                            self.cfg.max_workers)
                continue
            self.scale_workers(int(count))

    def _write_run_config(self) -> None:
        write_config(self.cfg, self.run_dir / "config.json")
        self.revision = git_revision()
        (self.run_dir / "git_revision").write_text(self.revision + "\n")

    def _on_stats(self, key: str, payload: bytes) -> None:
        try:
            stats = decode(payload, ServiceStats)
        except ProtocolError:
            log.warning("bad stats message on %s", key)
            return
        if not self.started_it(stats, key):
            if (stats.service, stats.instance) not in self.strangers and len(self.strangers) < 100:
                self.strangers.add((stats.service, stats.instance))
                log.warning("stats beats from %s/%s, which this run did not start: ignored", stats.service, stats.instance)
            return
        self._track_policy_version(stats)
        if stats.service == "dynamics-learner":
            with self._lock:
                row = live_row(stats.values, self.live_history[-1] if self.live_history else None,
                               time.monotonic() - self.progress.started)
                if row is not None:
                    self.live_history.append(row)
        self.progress.on_stats(stats)

    def _track_policy_version(self, stats: ServiceStats) -> None:
        """Record published (policy-learner) and in-use (env-worker) policy versions as they change."""
        version = stats.values.get("policy_version")
        if version is None or stats.service not in ("policy-learner", "env-worker"):
            return
        previous = self.progress.stats.get((stats.service, stats.instance))
        if previous is None or previous.values.get("policy_version") != version:
            with self._lock:
                self.policy_timeline.append((time.monotonic() - self.progress.started, stats.service,
                                             stats.instance, version))

    def _on_graph(self, key: str, payload: bytes) -> None:
        try:
            report = decode(payload, GraphReport)
            fresh = self.report_versions.take(f"graph/{report.kind}", report.weights_version, self.published_version())
        except ProtocolError as exc:
            log.warning("bad graph report on %s: %s", key, exc)
            return
        if not fresh:  # a repeat or an older version: the history has it, or never will
            return
        with self._lock:
            if self._stop.is_set():  # the run has stopped: the summary is the graph it stopped on, not a later one
                return
            self.last_report = report
            undecided = {} if report.undecided is None else {"undecided_entries": int(report.undecided.sum())}
            self.history.append({"time": time.monotonic() - self.progress.started, "env_steps": report.env_steps,
                                 "updates": report.updates, "num_heldout": report.num_heldout,
                                 **report.metrics, **undecided})
        self.progress.on_report(report)

    def _on_local(self, key: str, payload: bytes) -> None:
        try:
            report = decode(payload, LocalGraphReport)
            fresh = self.report_versions.take(f"local/{report.kind}", report.weights_version, self.published_version())
        except ProtocolError as exc:
            log.warning("bad local-graph report on %s: %s", key, exc)
            return
        if not fresh:
            return
        with self._lock:
            self.last_local = report
            self.progress.on_local_report(report)
            self.local_history.append({"time": time.monotonic() - self.progress.started, "env_steps": report.env_steps,
                                       "updates": report.updates, **report.metrics})

    def run(self) -> dict:
        """Start everything, supervise until a stop condition, then stop and report."""
        started = time.monotonic()
        handlers = {sig: signal.signal(sig, lambda *_: self.request_stop("interrupted"))
                    for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            self.start()
            while not self._stop.wait(0.2):
                now = time.monotonic()
                self._apply_scale_requests()
                try:
                    if any([proc.check(now) for proc in list(self.processes.values())]):
                        self._write_process_table()
                except FatalServiceError as exc:
                    self.failure = str(exc)
                    self.request_stop(f"failed: {exc}")
                self.progress.show(self.restarts())
                self._check_budget(now - started)
        finally:
            for sig, previous in handlers.items():
                signal.signal(sig, previous)
            self.progress.show(self.restarts(), force=True)
            self.progress.finish()
            self.shutdown()
        return self.finish(time.monotonic() - started)

    def request_stop(self, reason: str) -> None:
        if not self.stop_reason:
            self.stop_reason = reason
        self._stop.set()

    def _check_budget(self, elapsed: float) -> None:
        """Stop when a rule says so, on the report it judged: one that came in meanwhile is dropped
        (with its history entry), so the summary shows the graph the rule stopped on (a stable graph
        with nothing undecided, say), not a newer one it never saw."""
        with self._lock:
            report, seen = self.last_report, len(self.history)
        reason = self.stop_rules.check(elapsed, report, self.progress.env_steps())
        if reason:
            with self._lock:
                self.last_report = report
                del self.history[seen:]
                self.request_stop(reason)

    def _pause_workers(self) -> None:
        self.bus.publish(topics.control(self.cfg.run_id, "env-worker"), encode(Control("pause", issued_at=time.time())))

    def restarts(self) -> int:
        return sum(p.restarts for p in self.processes.values())

    def shutdown(self) -> None:
        if hasattr(self, "bus"):
            try:
                self._own_stop = time.time()
                self.bus.publish(topics.control(self.cfg.run_id, "all"), encode(Control("stop", issued_at=self._own_stop)))
            except Exception:
                log.exception("could not broadcast stop")
        stop_all(list(self.processes.values()) + self.retired)
        if hasattr(self, "bus"):
            self.bus.close()
        if hasattr(self, "router"):
            self.router.close()

    def finish(self, wall_seconds: float) -> dict:
        """summary.json, the final graph, the evaluation and the plots (:mod:`services.supervisor.analysis`)."""
        cfg = self.cfg
        budget_at = self.stop_rules.budget_reached_at
        facts = {"run_id": cfg.run_id, "env": cfg.env, "method": cfg.method,
                 "env_options": env_entry(cfg.env).kwargs(cfg.env_options), "seed": cfg.seed, "workers": cfg.workers,
                 "env_steps": self.progress.env_steps(), "updates": self.progress.updates(),
                 "wall_seconds": round(wall_seconds, 1), "stopped_because": self.stop_reason or "stopped",
                 "restarts": self.restarts(), "transitions_lost": self.progress.transitions_lost(),
                 "catch_up_seconds": round(wall_seconds - budget_at, 1) if budget_at is not None else 0.0,
                 "git_revision": self.revision or git_revision()}
        task = {key: value for key in ("success_rate", "return_mean", "stages_mean")
                if (value := self.progress.mean("env-worker", key)) is not None}
        if task:
            facts["task"] = {**task, "episodes": int(self.progress.value("env-worker", "episodes")),
                             "evaluation": "the env-workers' last 100 episodes each (the collection policy)"}
        facts.update(skill_facts(self.progress.stats.get(("policy-learner", "0"))))
        facts.update(slot_facts(self.progress.stats.get(("factor-extractor", "0"))))
        facts.update(label_facts(self.progress.stats.get(("factor-extractor", "0"))))
        with self._lock:
            record = RunRecord(facts, self.last_report, list(self.history), failure=self.failure,
                               policy_timeline=list(self.policy_timeline), local_report=self.last_local,
                               local_history=list(self.local_history), live_history=list(self.live_history))
            if cfg.collector != "random":
                record.policy_stats = {ident: dict(s.values) for ident, s in self.progress.stats.items()}
        return analyse(cfg, self.run_dir, record, self.progress.stream)
