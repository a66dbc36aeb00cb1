"""(a) End-to-end transitions/s from env-workers to the dynamics-learner: Zenoh vs in-memory.

Both runs use the unchanged service code (env-worker ``run`` publishing unthrottled batches, the
dynamics-learner ``run`` ingesting them with training disabled by a huge warm-up), and count the
env steps the learner has ingested, from its own stats beats, over a fixed window.

* in-memory: every service is a thread of this process on one ``InMemoryBus``;
* Zenoh: a router in this process, every service its own OS process (the ``causeway run`` layout).

    python -m benchmarks.bench_transport [--seconds 20] [--workers 1]
"""
from __future__ import annotations

import argparse
import dataclasses
import tempfile
import threading
import time

from proto import topics
from proto.codec import decode
from proto.messages import ServiceStats
from services.runtime.config import build_config
from services.supervisor.config import RunConfig

RUN = dict(graph="full", num_objects=10, worker_max_steps_per_second=0.0, progress=False, metrics_base_port=0)
LEARNER = {"warmup_steps": 10**12, "replay_capacity": 100_000}


class IngestCounter:
    """Newest env_steps reported by the learner, with timestamps."""

    def __init__(self) -> None:
        self.samples: list[tuple[float, float]] = []
        self.lock = threading.Lock()

    def __call__(self, key: str, payload: bytes) -> None:
        stats = decode(payload, ServiceStats)
        with self.lock:
            self.samples.append((time.monotonic(), stats.values.get("env_steps", 0.0)))

    def rate(self, warmup: float, seconds: float) -> float:
        time.sleep(warmup)
        with self.lock:
            t0, s0 = self.samples[-1] if self.samples else (time.monotonic(), 0.0)
        time.sleep(seconds)
        with self.lock:
            t1, s1 = self.samples[-1]
        return (s1 - s0) / (t1 - t0)


def in_memory(seconds: float, workers: int) -> float:
    from services.supervisor.inprocess import InProcessStack
    cfg = build_config(RunConfig, **RUN, workers=workers, run_dir=tempfile.mkdtemp(prefix="causeway-bench-mem-"), run_id="bench-mem")
    stack = InProcessStack(cfg, services=("dynamics-learner",), config_overrides={"dynamics-learner": LEARNER})
    counter = IngestCounter()
    stack.transport().subscribe(topics.stats(stack.cfg.run_id, "dynamics-learner"), counter)
    stack.start()
    try:
        return counter.rate(5.0, seconds)
    finally:
        stack.stop()


def over_zenoh(seconds: float, workers: int) -> float:
    from services.bus.zenoh_transport import ZenohTransport
    from services.supervisor.supervisor import Supervisor
    from services.supervisor.wiring import MODULES, service_configs
    cfg = build_config(RunConfig, **RUN, workers=workers, router_port=0, run_dir=tempfile.mkdtemp(prefix="causeway-bench-zenoh-"),
                    run_id="bench-zenoh", dashboard_port=0, bus_auth=False)  # it starts an open router itself
    sup = Supervisor(cfg)
    sup.run_dir.mkdir(parents=True, exist_ok=True)
    from services.bus.router import start_router, wait_for_router
    sup.router = start_router(f"tcp/127.0.0.1:{sup.cfg.router_port}")
    wait_for_router(sup.connect)
    learner = dataclasses.replace(service_configs(sup.cfg, sup.connect)["dynamics-learner"], **LEARNER)
    sup.process("dynamics-learner", MODULES["dynamics-learner"], learner).start()
    for i in range(workers):
        sup.add_worker(i)
    bus = ZenohTransport(sup.connect)
    counter = IngestCounter()
    bus.subscribe(topics.stats(sup.cfg.run_id, "dynamics-learner"), counter)
    sup.bus = bus
    try:
        return counter.rate(8.0, seconds)
    finally:
        sup.shutdown()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--workers", type=int, default=1)
    args = p.parse_args()
    mem = in_memory(args.seconds, args.workers)
    zen = over_zenoh(args.seconds, args.workers)
    print(f"transitions/s reaching the learner, {args.workers} env-worker(s), Chemical full 10 objects, batches of 256")
    print(f"  in-memory (threads, one process) : {mem:10,.0f}")
    print(f"  Zenoh (router + processes)       : {zen:10,.0f}")
    print(f"  ratio Zenoh / in-memory          : {zen / mem:10.2f}  (target >= 0.9)")


if __name__ == "__main__":
    main()
