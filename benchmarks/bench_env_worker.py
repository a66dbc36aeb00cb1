"""Env steps/s of real env-worker processes against the raw environment, measured in the same run.

Raw: this process steps the environment with the same collection policy (no batching, no bus).
Worker: ``python -m services.env_worker`` processes publishing TransitionBatches to a Zenoh router
in this process; their rate is read from their own stats beats over a fixed window.

    python -m benchmarks.bench_env_worker [--env manipulation] [--seconds 30] [--workers 1 2] [--robosuite-controller]

``--workers`` with no numbers measures the raw environment only. ``--robosuite-controller``
(manipulation) also measures the raw environment stepped through robosuite's own per-sub-step
controller path, which gives the same trajectories (see :mod:`envs.manipulation_control`).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from proto import topics
from proto.codec import decode
from proto.messages import ServiceStats
from services.runtime.config import build_config
from services.bus.router import free_tcp_port, start_router, wait_for_router
from services.bus.zenoh_transport import ZenohTransport
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.runtime.config import to_environ
from services.supervisor.processes import ManagedProcess, stop_all


def raw_rate(env_name: str, seconds: float, robosuite_controller: bool = False) -> tuple[float, float]:
    """Steps per second of wall time and per second of this process's CPU time (the latter does not
    drop when other processes share the cores)."""
    core = EnvWorkerCore(build_config(EnvWorkerConfig, env=env_name))
    env, policy, obs = core.env, core.policy, core.observation
    if robosuite_controller:
        env.unwrapped.scene.robosuite_controller = True
    steps, t0, cpu0 = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds:
        obs, _, term, trunc, _ = env.step(policy.act(obs) if core.spec.action_kind != "categorical" else int(policy.act(obs)[0]))
        steps += 1
        if term or trunc:
            obs, _ = env.reset()
    return steps / (time.perf_counter() - t0), steps / (time.process_time() - cpu0)


def worker_rate(env_name: str, workers: int, seconds: float, batch_steps: int) -> float:
    port = free_tcp_port()
    router = start_router(f"tcp/127.0.0.1:{port}")
    connect = f"tcp/127.0.0.1:{port}"
    wait_for_router(connect)
    bus = ZenohTransport(connect)
    beats: dict[str, list[tuple[float, float]]] = {}
    bus.subscribe(topics.stats("bench", "env-worker"), lambda k, p: beats.setdefault(k, []).append(
        (time.monotonic(), decode(p, ServiceStats).values["env_steps"])))
    run_dir = Path(tempfile.mkdtemp(prefix="causeway-bench-worker-"))
    procs = [ManagedProcess(f"env-worker-{i}", "services.env_worker", to_environ(build_config(EnvWorkerConfig, 
        run_id="bench", zenoh_connect=connect, run_dir=str(run_dir), instance=str(i), worker_index=i,
        env=env_name, batch_steps=batch_steps)), run_dir / f"worker-{i}.log") for i in range(workers)]
    for p in procs:
        p.start()
    try:
        deadline = time.monotonic() + 120
        while len(beats) < workers or min(len(v) for v in beats.values()) < 2:
            if time.monotonic() > deadline:
                raise RuntimeError(f"workers did not report; see {run_dir}")
            time.sleep(0.2)
        start = {k: v[-1] for k, v in beats.items()}
        time.sleep(seconds)
        return sum((v[-1][1] - start[k][1]) / (v[-1][0] - start[k][0]) for k, v in beats.items())
    finally:
        stop_all(procs)
        bus.close()
        router.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="manipulation")
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    p.add_argument("--batch-steps", type=int, default=64)
    p.add_argument("--robosuite-controller", action="store_true",
                   help="manipulation: also time the raw env on robosuite's own controller path")
    args = p.parse_args()
    raw, raw_cpu = raw_rate(args.env, args.seconds)
    print(f"{args.env}: env steps/s, collection policy of the env-worker, batches of {args.batch_steps}")
    print(f"  raw environment (this process)   : {raw:9.1f}   per CPU-second {raw_cpu:9.1f}")
    if args.robosuite_controller:
        ref, ref_cpu = raw_rate(args.env, args.seconds, robosuite_controller=True)
        print(f"  raw, robosuite's controller path : {ref:9.1f}   per CPU-second {ref_cpu:9.1f}"
              f"   speed-up {raw_cpu / ref_cpu:5.2f} (CPU)")
    for n in args.workers:
        rate = worker_rate(args.env, n, args.seconds, args.batch_steps)
        print(f"  {n} env-worker process(es), total : {rate:9.1f}   ratio to raw {rate / raw:5.2f}")


if __name__ == "__main__":
    main()
