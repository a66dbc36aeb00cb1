"""``causeway run``: the embedded default stack, wired in one readable place.

A Zenoh router runs inside this process (a Python session in router mode on 127.0.0.1, multicast
scouting off); every service runs as its own OS process connected to it. The supervisor restarts
crashed services (they resume from their checkpoints), shows live progress from the services' stats
beats and graph reports, stops on a target F1 or a time/step budget, and writes the run directory.

With ``--updates-per-env-step`` the env-step budget does not stop the run at once: the env-workers
are paused (Control ``pause``, repeated every second so a restarted worker pauses too) and the run
stops when a graph report comes from weights trained ``CATCH_UP_TOLERANCE`` x ratio x budget updates,
or after ``--catch-up-timeout-s``. So every collector ends with the same data and the same training,
however fast it collected.
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
from proto.messages import Control, EnvSpec, GraphReport, ServiceStats
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
from services.env_worker.core import env_kwargs
from services.supervisor.evaluation import CHEMICAL_ENVS, evaluate_run, plot_evaluation
from services.supervisor.final_graph import add_final_graph, final_graph
from services.supervisor.processes import FatalServiceError, ManagedProcess, stop_all
from services.supervisor.progress import Progress

log = logging.getLogger("supervisor")
CATCH_UP_TOLERANCE = 0.98


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

    probe = worker_config(dataclasses.replace(cfg, metrics_base_port=0), "", 0)
    return make_env(cfg.env, **env_kwargs(probe)).unwrapped.env_spec().action_kind == "categorical"


def service_configs(cfg: RunConfig, connect: str, worker_index: int = 0) -> dict[str, object]:
    """The wiring: what each service is told (all of it lands in <run_dir>/config.json)."""
    common = dict(run_id=cfg.run_id, zenoh_connect=connect, run_dir=cfg.run_dir)
    port = (lambda offset: cfg.metrics_base_port + offset if cfg.metrics_base_port else 0)
    learner = DynamicsLearnerConfig(**common, metrics_port=port(1), seed=cfg.seed, lr=cfg.lr,
                                    lr_decay_updates=cfg.lr_decay_updates, lr_final=cfg.lr_final,
                                    batch_size=cfg.batch_size, replay_capacity=cfg.replay_capacity,
                                    feature_hidden=cfg.feature_dim,
                                    feature_dim=cfg.feature_dim, predictor_hidden=cfg.predictor_hidden,
                                    cmi_threshold=cfg.cmi_threshold, publish_every_s=cfg.publish_every_s,
                                    checkpoint_every_s=cfg.checkpoint_every_s,
                                    updates_per_env_step=cfg.updates_per_env_step)
    evaluator = GraphEvaluatorConfig(**common, metrics_port=port(2), cmi_threshold=cfg.cmi_threshold,
                                     min_interval_s=cfg.eval_interval_s, seed=cfg.seed,
                                     checkpoint_every_s=cfg.checkpoint_every_s)
    dashboard = DashboardConfig(**common, metrics_port=port(3), http_host="127.0.0.1",
                                http_port=cfg.dashboard_port, watch_run=cfg.run_id)
    policy = PolicyLearnerConfig(**common, metrics_port=port(4), algo=cfg.collector if cfg.collector != "random" else "ppo",
                                 seed=cfg.seed, scored=cfg.intrinsic != "none", max_policy_lag=cfg.max_policy_lag,
                                 abstraction=cfg.abstraction, intrinsic_coef=cfg.intrinsic_coef,
                                 skills=cfg.collector == "ppo" and cfg.env == "manipulation", hide=cfg.policy_hide,
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
        self.policy_timeline: list[tuple[float, str, str, float]] = []
        """(seconds since start, service, instance, policy version) whenever a version changes."""
        self.budget_reached_at: float | None = None
        self._last_pause = -1e9

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
            stats = decode(payload, ServiceStats)
        except ProtocolError:
            log.warning("bad stats message on %s", key)
            return
        self._track_policy_version(stats)
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
            if cfg.updates_per_env_step > 0:
                self._catch_up(elapsed)
            else:
                self.request_stop(f"env step budget {cfg.max_env_steps} reached")
        if cfg.max_seconds and elapsed >= cfg.max_seconds:
            self.request_stop(f"time budget {cfg.max_seconds:.0f}s reached")

    def _catch_up(self, elapsed: float) -> None:
        """Env-step budget reached with a ratio set: keep the env-workers paused until the graph
        reflects a learner that made its share of updates (or the catch-up timeout passes)."""
        cfg = self.cfg
        if self.budget_reached_at is None:
            self.budget_reached_at = elapsed
            log.warning("env step budget %d reached: env-workers paused until the learner catches up", cfg.max_env_steps)
        if elapsed - self._last_pause >= 1.0:
            self._last_pause = elapsed
            self.bus.publish(topics.control(cfg.run_id, "env-worker"), encode(Control("pause", issued_at=time.time())))
        report = self.last_report
        if learner_caught_up(report, cfg.updates_per_env_step, cfg.max_env_steps):
            self.request_stop(f"env step budget {cfg.max_env_steps} reached, learner caught up ({report.updates} updates)")
        elif elapsed - self.budget_reached_at >= cfg.catch_up_timeout_s:
            self.request_stop(f"env step budget {cfg.max_env_steps} reached, learner did not catch up "
                              f"in {cfg.catch_up_timeout_s:.0f}s")

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
                "catch_up_seconds": (round(wall_seconds - self.budget_reached_at, 1)
                                     if self.budget_reached_at is not None else 0.0),
                "git_revision": _git_revision()}
        content = reporting.summary(report, base, history)
        final = self._final_graph() if report is not None and cfg.evaluate and not self.failure else None
        if cfg.collector != "random":
            with self._lock:
                stats = {ident: dict(s.values) for ident, s in self.progress.stats.items()}
                content["policy"] = reporting.policy_summary(stats, list(self.policy_timeline))
            reporting.plot_policy(content["policy"], self.run_dir / "policy.png")
        if report is not None and cfg.evaluate and cfg.env in CHEMICAL_ENVS and not self.failure:
            content["evaluation"] = self._evaluate(report)
        if report is not None:
            reporting.plot_graphs(report, self.run_dir / "graph.png")
            reporting.plot_object_graphs(report, self.run_dir / "object_graph.png")
            reporting.plot_learning_curve(history, self.run_dir / "learning_curve.png")
        if final is not None:
            add_final_graph(content, final, self.run_dir)
        reporting.write_summary(self.run_dir / "summary.json", content)
        if "prediction" in content.get("evaluation", {}):
            plot_evaluation(content["evaluation"], self.run_dir / "evaluation.png")
        return content

    def _final_graph(self) -> GraphReport | None:
        """The final model's graph on all held-out data (services.supervisor.final_graph); a failure
        is logged and leaves the summary with the live reports only."""
        cfg = self.cfg
        self.progress.stream.write("final graph: CMI of the final model on every held-out transition ...\n")
        try:
            final = final_graph(self.run_dir, service_configs(cfg, self.connect)["graph-evaluator"], run_env_spec(cfg))
        except Exception:  # noqa: BLE001 - the run itself is done
            log.exception("final graph evaluation failed")
            return None
        if final is not None:
            self.progress.stream.write(f"final graph: {final.num_heldout:,} held-out transitions, "
                                       f"{reporting.score_line(final.metrics)}\n")
        return final

    def _evaluate(self, report: GraphReport) -> dict:
        """Chapter 3's evaluations on this run's final models (see services.supervisor.evaluation);
        a failure is recorded in the summary, never raised: the run itself is done."""
        cfg = self.cfg
        configs = service_configs(cfg, self.connect)
        self.progress.stream.write("evaluating the run's model (prediction ID/OOD"
                                   + (", Match" if cfg.task == "match" else "") + ") ...\n")
        try:
            policy = load_policy(self.run_dir, configs["policy-learner"], cfg) if cfg.collector != "random" else None
            return evaluate_run(self.run_dir, cfg.env, env_kwargs(configs["env-worker"]), report, policy)
        except Exception as exc:  # noqa: BLE001 - reported in the summary
            log.exception("post-run evaluation failed")
            return {"error": f"{type(exc).__name__}: {exc}"}


def learner_caught_up(report: GraphReport | None, ratio: float, max_env_steps: int) -> bool:
    """Whether ``report`` scores weights trained for (about) ``ratio`` x ``max_env_steps`` updates.

    The learner never exceeds its ratio of the steps it ingested, so such weights have also seen
    (about) the whole budget."""
    return report is not None and report.updates >= CATCH_UP_TOLERANCE * ratio * max_env_steps


def load_policy(run_dir: Path, policy_cfg: PolicyLearnerConfig, cfg: RunConfig, deterministic: bool = True):
    """The policy-learner's last checkpointed policy as ``obs -> action`` (the mode, or sampled), or None.
    A policy over skills (``policy_cfg.skills``) returns the option to run next."""
    from services.policy_learner.core import PolicyLearnerCore

    path = run_dir / "checkpoints" / "policy-learner-0.pt"
    if not path.exists():
        return None
    core = PolicyLearnerCore(policy_cfg, run_env_spec(cfg))
    core.restore(path)
    return lambda obs: core.agent.act(obs, deterministic=deterministic)


def run_env_spec(cfg: RunConfig) -> EnvSpec:
    """The EnvSpec of the run's environment, as its first env-worker builds it."""
    from envs import make_env

    return make_env(cfg.env, **env_kwargs(worker_config(cfg, "", 0))).unwrapped.env_spec()


def _git_revision() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                              check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def print_summary(content: dict) -> None:
    keys = ("env", "graph", "seed", "env_steps", "updates", "wall_seconds", "stopped_because", "accuracy",
            "precision", "recall", "f1", "roc_auc", "best_threshold_f1")
    shown = {k: content.get(k) for k in keys}
    if "final_graph" in content:
        final = content["final_graph"]
        shown["final_graph"] = {k: final.get(k) for k in ("num_heldout", "accuracy", "f1", "best_threshold_f1",
                                                          "with_self_best_threshold_f1",
                                                          "with_self_best_threshold_accuracy")}
    print(json.dumps(shown, indent=1))
