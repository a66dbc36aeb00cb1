"""``causeway run``: the embedded default stack, wired in one readable place.

A Zenoh router runs inside this process (a Python session in router mode on 127.0.0.1, multicast
scouting off); every service runs as its own OS process connected to it. The supervisor restarts
crashed services (they resume from their checkpoints), shows live progress from the services' stats
beats and graph reports, stops on a target F1 or a time/step budget, and writes the run directory.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import queue
import signal
import subprocess
import threading
import time
from pathlib import Path

from proto import topics
from proto.codec import ProtocolError, decode, encode
from proto.messages import Control, GraphReport, ServiceStats
from services.bus.router import free_tcp_port, start_router, wait_for_router
from services.bus.zenoh_transport import ZenohTransport
from services.dashboard.config import DashboardConfig
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.env_worker.config import EnvWorkerConfig
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.policy_learner.config import PolicyLearnerConfig
from services.runtime.config import to_environ, write_config
from services.supervisor import report as reporting
from services.supervisor.config import COLLECTORS, INTRINSIC, TASKS, RunConfig
from services.supervisor.processes import FatalServiceError, ManagedProcess, stop_all
from services.supervisor.progress import Progress

log = logging.getLogger("supervisor")


def resolve(cfg: RunConfig) -> RunConfig:
    """Fill in the derived defaults: run id, run directory, router port, the task's environment."""
    if cfg.collector not in COLLECTORS or cfg.intrinsic not in INTRINSIC or cfg.task not in TASKS:
        raise ValueError(f"collector must be one of {COLLECTORS}, intrinsic one of {INTRINSIC}, "
                         f"task one of {tuple(TASKS)}; got {cfg.collector!r}, {cfg.intrinsic!r}, {cfg.task!r}")
    if cfg.intrinsic != "none" and cfg.collector == "random":
        raise ValueError("an intrinsic reward needs a policy to train: use --collector ppo or sac")
    cfg = dataclasses.replace(cfg, env=TASKS[cfg.task] or cfg.env)
    if cfg.collector == "sac" and _discrete_actions(cfg):
        raise ValueError(f"SAC needs continuous actions; {cfg.env} has discrete ones (use --collector ppo)")
    run_id = cfg.run_id or (Path(cfg.run_dir).name if cfg.run_dir else
                            f"{cfg.env}-{Path(cfg.graph).stem}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}")
    run_id = "".join(c if c.isalnum() or c in "_.-" else "-" for c in run_id)
    return dataclasses.replace(cfg, run_id=run_id, run_dir=cfg.run_dir or f"runs/{run_id}",
                               router_port=cfg.router_port or free_tcp_port())


def _discrete_actions(cfg: RunConfig) -> bool:
    from envs import make_env
    from services.env_worker.core import env_kwargs

    probe = worker_config(dataclasses.replace(cfg, metrics_base_port=0), "", 0)
    return make_env(cfg.env, **env_kwargs(probe)).unwrapped.env_spec().action_kind == "categorical"


def service_configs(cfg: RunConfig, connect: str, worker_index: int = 0) -> dict[str, object]:
    """The wiring: what each service is told (all of it lands in <run_dir>/config.json)."""
    common = dict(run_id=cfg.run_id, zenoh_connect=connect, run_dir=cfg.run_dir)
    port = (lambda offset: cfg.metrics_base_port + offset if cfg.metrics_base_port else 0)
    learner = DynamicsLearnerConfig(**common, metrics_port=port(1), seed=cfg.seed, lr=cfg.lr,
                                    batch_size=cfg.batch_size, feature_hidden=cfg.feature_dim,
                                    feature_dim=cfg.feature_dim, predictor_hidden=cfg.predictor_hidden,
                                    cmi_threshold=cfg.cmi_threshold, publish_every_s=cfg.publish_every_s,
                                    checkpoint_every_s=cfg.checkpoint_every_s)
    evaluator = GraphEvaluatorConfig(**common, metrics_port=port(2), cmi_threshold=cfg.cmi_threshold,
                                     min_interval_s=cfg.eval_interval_s, seed=cfg.seed,
                                     checkpoint_every_s=cfg.checkpoint_every_s)
    dashboard = DashboardConfig(**common, metrics_port=port(3), http_host="127.0.0.1",
                                http_port=cfg.dashboard_port, watch_run=cfg.run_id)
    policy = PolicyLearnerConfig(**common, metrics_port=port(4), algo=cfg.collector if cfg.collector != "random" else "ppo",
                                 seed=cfg.seed, scored=cfg.intrinsic != "none", max_policy_lag=cfg.max_policy_lag,
                                 abstraction=cfg.abstraction, intrinsic_coef=cfg.intrinsic_coef,
                                 checkpoint_every_s=cfg.checkpoint_every_s)
    intrinsic = IntrinsicRewardConfig(**common, metrics_port=port(5),
                                      reward=cfg.intrinsic if cfg.intrinsic != "none" else "preddiff")
    return {"dynamics-learner": learner, "graph-evaluator": evaluator, "dashboard": dashboard,
            "policy-learner": policy, "intrinsic-reward": intrinsic,
            "env-worker": worker_config(cfg, connect, worker_index)}


def learning_services(cfg: RunConfig) -> tuple[str, ...]:
    """The services besides env-workers and dashboard that ``cfg`` asks for."""
    return (("dynamics-learner", "graph-evaluator") + (("policy-learner",) if cfg.collector != "random" else ())
            + (("intrinsic-reward",) if cfg.intrinsic != "none" else ()))


def worker_config(cfg: RunConfig, connect: str, index: int) -> EnvWorkerConfig:
    port = cfg.metrics_base_port + 10 + index if cfg.metrics_base_port else 0
    return EnvWorkerConfig(run_id=cfg.run_id, zenoh_connect=connect, run_dir=cfg.run_dir, metrics_port=port,
                           instance=str(index), env=cfg.env, graph=cfg.graph, num_objects=cfg.num_objects,
                           cpt_seed=cfg.cpt_seed, seed=cfg.seed, worker_index=index,
                           max_steps_per_second=cfg.steps_per_second, follow_policy=cfg.collector != "random")


MODULES = {"env-worker": "services.env_worker", "dynamics-learner": "services.dynamics_learner",
           "graph-evaluator": "services.graph_evaluator", "dashboard": "services.dashboard",
           "policy-learner": "services.policy_learner", "intrinsic-reward": "services.intrinsic_reward"}


class Supervisor:
    """Owns the router, the service processes and the run directory of one local run."""

    def __init__(self, cfg: RunConfig) -> None:
        self.cfg = resolve(cfg)
        self.run_dir = Path(self.cfg.run_dir)
        self.connect = f"tcp/127.0.0.1:{self.cfg.router_port}"
        self.processes: dict[str, ManagedProcess] = {}
        self.progress = Progress(interactive=None if self.cfg.progress else False,
                                 every_s=10.0 if self.cfg.progress else 1e9)
        self.history: list[dict[str, float]] = []
        self.last_report: GraphReport | None = None
        self.stop_reason = ""
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._own_stop = -1.0
        self.pending_scale: queue.Queue[str] = queue.Queue()
        self.retired: list[ManagedProcess] = []
        self.next_worker_index = 0
        self.failure = ""

    @property
    def dashboard_url(self) -> str | None:
        port = self.cfg.dashboard_port
        return f"http://127.0.0.1:{port}/?run={self.cfg.run_id}" if port else None

    def process(self, name: str, module: str, service_cfg: object) -> ManagedProcess:
        proc = ManagedProcess(name, module, to_environ(service_cfg), self.run_dir / "logs" / f"{name}.log")
        self.processes[name] = proc
        return proc

    def start(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._write_run_config()
        self.router = start_router(f"tcp/127.0.0.1:{self.cfg.router_port}")
        wait_for_router(self.connect)
        self.bus = ZenohTransport(self.connect)
        self.bus.subscribe(topics.stats(self.cfg.run_id), self._on_stats)
        self.bus.subscribe(topics.graph(self.cfg.run_id), self._on_graph)
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

    def scale_workers(self, count: int) -> None:
        """Add workers (new indices, so new seeds) or retire the newest ones; nothing else restarts.

        A retired worker gets SIGTERM, finishes and publishes the batch it is collecting, and exits."""
        if count < 0:
            raise ValueError(f"cannot scale env-worker to {count}")
        current = self.worker_indices()
        for _ in range(count - len(current)):
            self.next_worker_index = max(self.next_worker_index, max(current, default=-1) + 1)
            self.add_worker(self.next_worker_index)
            self.next_worker_index += 1
        for index in sorted(current, reverse=True)[: max(len(current) - count, 0)]:
            proc = self.processes.pop(f"env-worker-{index}")
            proc.terminate()
            self.retired.append(proc)
        self._write_process_table()
        log.warning("env-worker scaled from %d to %d", len(current), count)

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
            if service != "env-worker" or not count.isdigit():
                log.warning("ignored scale request %r (expected env-worker=N)", argument)
                continue
            self.scale_workers(int(count))

    def _write_run_config(self) -> None:
        write_config(self.cfg, self.run_dir / "config.json")
        (self.run_dir / "git_revision").write_text(_git_revision() + "\n")

    def _on_stats(self, key: str, payload: bytes) -> None:
        try:
            self.progress.on_stats(decode(payload, ServiceStats))
        except ProtocolError:
            log.warning("bad stats message on %s", key)

    def _on_graph(self, key: str, payload: bytes) -> None:
        try:
            report = decode(payload, GraphReport)
        except ProtocolError:
            log.warning("bad graph report on %s", key)
            return
        with self._lock:
            self.last_report = report
            self.history.append({"time": time.monotonic() - self.progress.started, "env_steps": report.env_steps,
                                 "updates": report.updates, **report.metrics})
        self.progress.on_report(report)

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
        cfg = self.cfg
        report = self.last_report
        if cfg.target_f1 and report is not None and report.metrics.get(cfg.target_metric, 0.0) >= cfg.target_f1:
            self.request_stop(f"target {cfg.target_metric} {cfg.target_f1} reached")
        elif cfg.max_env_steps and self.progress.env_steps() >= cfg.max_env_steps:
            self.request_stop(f"env step budget {cfg.max_env_steps} reached")
        elif cfg.max_seconds and elapsed >= cfg.max_seconds:
            self.request_stop(f"time budget {cfg.max_seconds:.0f}s reached")

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
        cfg = self.cfg
        with self._lock:
            report, history = self.last_report, list(self.history)
        base = {"run_id": cfg.run_id, "env": cfg.env, "graph": cfg.graph if cfg.env.startswith("chemical") else None, "num_objects": cfg.num_objects,
                "seed": cfg.seed, "workers": cfg.workers, "env_steps": self.progress.env_steps(),
                "updates": self.progress.updates(), "wall_seconds": round(wall_seconds, 1),
                "stopped_because": self.stop_reason or "stopped", "restarts": self.restarts(),
                "git_revision": _git_revision()}
        content = reporting.summary(report, base, history)
        reporting.write_summary(self.run_dir / "summary.json", content)
        if report is not None:
            reporting.plot_graphs(report, self.run_dir / "graph.png")
            reporting.plot_object_graphs(report, self.run_dir / "object_graph.png")
            reporting.plot_learning_curve(history, self.run_dir / "learning_curve.png")
        return content


def _git_revision() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                              check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def print_summary(content: dict) -> None:
    keys = ("env", "graph", "seed", "env_steps", "updates", "wall_seconds", "stopped_because", "accuracy",
            "precision", "recall", "f1", "roc_auc", "best_threshold_f1")
    print(json.dumps({k: content.get(k) for k in keys}, indent=1))
