"""The same services in one process, over the in-memory transport (debugging, tests, benchmarks).

Each service's unchanged ``run(cfg, transport)`` runs in its own thread with its own
``InMemoryTransport`` on one shared hub; only the transport differs from the distributed stack.
"""
from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Callable

from proto import topics
from proto.codec import encode
from proto.messages import Control
from services.bus.memory import InMemoryBus, InMemoryTransport
from services.dashboard import service as dashboard_service
from services.dynamics_learner import service as learner_service
from services.env_worker import service as worker_service
from services.factor_extractor import service as extractor_service
from services.graph_evaluator import service as evaluator_service
from services.intrinsic_reward import service as intrinsic_service
from services.policy_learner import service as policy_service
from services.supervisor.config import RunConfig
from services.supervisor.wiring import learning_services, resolve, service_configs, worker_config

log = logging.getLogger("inprocess")


class InProcessStack:
    """env-workers and the learning services ``cfg`` asks for (or ``services``) as threads sharing
    one in-memory bus."""

    def __init__(self, cfg: RunConfig, services: tuple[str, ...] | None = None,
                 config_overrides: dict[str, dict] | None = None) -> None:
        self.cfg = resolve(dataclasses.replace(cfg, metrics_base_port=0))
        services = learning_services(self.cfg) if services is None else services
        self.bus = InMemoryBus()
        self.control = InMemoryTransport(self.bus)
        configs = service_configs(self.cfg, "memory")
        overrides = config_overrides or {}
        runners: dict[str, Callable] = {"dynamics-learner": learner_service.run, "graph-evaluator": evaluator_service.run,
                                        "dashboard": dashboard_service.run, "policy-learner": policy_service.run,
                                        "intrinsic-reward": intrinsic_service.run, "factor-extractor": extractor_service.run}
        self.threads: list[threading.Thread] = []
        self.errors: list[BaseException] = []
        for name in services:
            cfg_ = dataclasses.replace(configs[name], **overrides.get(name, {}))
            self._thread(name, runners[name], cfg_)
        for i in range(self.cfg.workers):
            cfg_ = dataclasses.replace(worker_config(self.cfg, "memory", i), metrics_port=0,
                                       **overrides.get("env-worker", {}))
            self._thread(f"env-worker-{i}", worker_service.run, cfg_)

    def _thread(self, name: str, target: Callable, cfg: object) -> None:
        def body() -> None:
            try:
                target(cfg, InMemoryTransport(self.bus))
            except BaseException as exc:  # surfaced by stop()
                log.exception("%s failed", name)
                self.errors.append(exc)
        self.threads.append(threading.Thread(target=body, name=name, daemon=True))

    def transport(self) -> InMemoryTransport:
        """A fresh endpoint on the shared hub (to watch topics, inject messages, ...)."""
        return InMemoryTransport(self.bus)

    def start(self) -> "InProcessStack":
        for t in self.threads:
            t.start()
        return self

    def stop(self, timeout: float = 30.0) -> None:
        self.control.publish(topics.control(self.cfg.run_id, "all"), encode(Control("stop", issued_at=time.time())))
        deadline = time.monotonic() + timeout
        for t in self.threads:
            t.join(max(deadline - time.monotonic(), 0.01))
        alive = [t.name for t in self.threads if t.is_alive()]
        if alive or self.errors:
            raise RuntimeError(f"in-process stack did not stop cleanly: alive {alive}, errors {self.errors!r}")
