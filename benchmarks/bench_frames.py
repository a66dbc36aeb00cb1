"""Bus cost of the frames topic (issue 24, item 5): frames/s from an env-worker to a subscriber, Zenoh vs
in-process, for the frames the factor-extractor gets (chemical-pixels, 32x32 RGB, 4 objects).

The unchanged env-worker ``run`` publishes unthrottled FrameBatches (``--publish-frames``); a subscriber
in this process decodes (validates) each one and counts its frames:

* in-process: the worker a thread of this process on one ``InMemoryBus``, the subscriber on the same bus;
* Zenoh: a router in this process, the worker its own OS process (the ``causeway run`` layout).

Both workers run from the start, and take turns: one is paused (the ``pause`` control command) while
the other is measured for a window, for ``--rounds`` rounds. The ratio of each round's two rates is
taken, so a change of the machine's load between rounds does not count as bus cost; the median of the
rounds is the issue's figure (goal >= 0.9). First, ``EnvWorkerCore.collect_frames`` and ``encode`` alone
(no bus, no service loop) give the worker's own ceiling.

``--capacity`` also measures what each bus carries with no env behind it: one real FrameBatch, encoded
once, published back to back to the same decoding subscriber (the two buses again taking turns).

    python -m benchmarks.bench_frames [--window 10] [--rounds 3] [--batch-steps 256] [--stride 1] [--capacity]
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from proto import topics
from proto.codec import decode, encode
from proto.messages import Control, FrameBatch
from services.env_worker.config import EnvWorkerConfig
from services.runtime.config import build_config, to_environ

REPO = Path(__file__).resolve().parents[1]
MEM_RUN, ZENOH_RUN = "bench-frames-mem", "bench-frames-zenoh"


class FrameCounter:
    """Decodes every FrameBatch it is given and records when it came, with its frames, steps and bytes."""

    def __init__(self) -> None:
        self.events: list[tuple[float, int, int, int]] = []
        self.lock = threading.Lock()

    def __call__(self, key: str, payload: bytes) -> None:
        batch = decode(payload, FrameBatch)
        with self.lock:
            self.events.append((time.monotonic(), len(batch.frames), len(batch), len(payload)))

    @property
    def frames(self) -> int:
        with self.lock:
            return len(self.events)

    def rates(self, seconds: float) -> dict[str, float]:
        """Frames, steps and bytes per second of the batches that arrive in the next ``seconds``: what came
        after the window's first arrival, over the time from it to the last (a batch arrives whole)."""
        t0 = time.monotonic()
        time.sleep(seconds)
        with self.lock:
            window = [e for e in self.events if e[0] >= t0]
        if len(window) < 2:
            raise RuntimeError(f"{len(window)} batches in {seconds} s: measure over a longer --window")
        dt = window[-1][0] - window[0][0]
        return {name: sum(e[i] for e in window[1:]) / dt for i, name in ((1, "frames"), (2, "steps"), (3, "bytes"))}


def worker_config(args: argparse.Namespace, **kw) -> EnvWorkerConfig:
    return build_config(EnvWorkerConfig, env="chemical-pixels", num_objects=4, graph="chain", publish_frames=True,
                        batch_steps=args.batch_steps, frame_stride=args.stride, max_steps_per_second=0.0,
                        run_dir=tempfile.mkdtemp(prefix="causeway-bench-frames-"), **kw)


def core_alone(args: argparse.Namespace) -> dict[str, float]:
    from services.env_worker.core import EnvWorkerCore

    core = EnvWorkerCore(worker_config(args))
    counter = FrameCounter()
    counter("", encode(core.collect_frames()))  # warm
    deadline = time.monotonic() + args.window
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            counter("", encode(core.collect_frames()))

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    rates = counter.rates(args.window)
    stop.set()
    thread.join(max(deadline - time.monotonic(), 0) + 30)
    return rates


class Turns:
    """Two running env-workers (in-process, Zenoh), each with its counter; one runs at a time."""

    def __init__(self, args: argparse.Namespace) -> None:
        from services.bus.memory import InMemoryBus, InMemoryTransport
        from services.bus.router import free_tcp_port, start_router, wait_for_router
        from services.bus.zenoh_transport import ZenohTransport
        from services.env_worker import service as worker_service

        self.memory = InMemoryTransport(InMemoryBus())
        self.counters = {"in-process": FrameCounter(), "zenoh": FrameCounter()}
        self.memory.subscribe(topics.frames(MEM_RUN), self.counters["in-process"])
        cfg = worker_config(args, run_id=MEM_RUN)
        self.thread = threading.Thread(target=worker_service.run, args=(cfg, InMemoryTransport(self.memory.bus)),
                                       daemon=True)
        connect = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.router = start_router(connect)
        wait_for_router(connect)
        self.zenoh = ZenohTransport(connect)
        self.zenoh.subscribe(topics.frames(ZENOH_RUN), self.counters["zenoh"])
        env = {**os.environ, **to_environ(worker_config(args, run_id=ZENOH_RUN, zenoh_connect=connect))}
        self.process = subprocess.Popen([sys.executable, "-m", "services.env_worker"], cwd=REPO, env=env,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.thread.start()

    def command(self, which: str, command: str) -> None:
        bus, run = (self.memory, MEM_RUN) if which == "in-process" else (self.zenoh, ZENOH_RUN)
        bus.publish(topics.control(run, "env-worker"), encode(Control(command, issued_at=time.time())))

    def wait_started(self, timeout: float = 300.0) -> None:
        deadline = time.monotonic() + timeout
        while not all(c.frames for c in self.counters.values()):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"an env-worker did not start (process exit {self.process.returncode})")
            time.sleep(0.2)

    def measure(self, which: str, settle: float, window: float) -> dict[str, float]:
        """``which``'s rates over ``window`` s, the other paused (after ``settle`` s for both to switch)."""
        other = "zenoh" if which == "in-process" else "in-process"
        self.command(other, "pause")
        self.command(which, "resume")
        time.sleep(settle)
        return self.counters[which].rates(window)

    def close(self) -> None:
        for which in self.counters:
            self.command(which, "stop")
        self.thread.join(60)
        try:
            self.process.wait(60)
        except subprocess.TimeoutExpired:
            self.process.kill()
        self.zenoh.close()
        self.router.close()


def capacity(args: argparse.Namespace) -> list[tuple[float, float]]:
    """What each bus carries without the env: one real FrameBatch, encoded once, published back to back by
    a thread of this process (Zenoh: through the router on loopback, BLOCK congestion control) to the
    decoding subscriber; in-process and Zenoh take turns, ``--rounds`` times. (in-process, Zenoh) frames/s."""
    from services.bus.memory import InMemoryBus, InMemoryTransport
    from services.bus.router import free_tcp_port, start_router, wait_for_router
    from services.bus.zenoh_transport import ZenohTransport
    from services.env_worker.core import EnvWorkerCore

    payload = encode(EnvWorkerCore(worker_config(args)).collect_frames())
    connect = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = start_router(connect)
    wait_for_router(connect)
    memory, sender, receiver = InMemoryTransport(InMemoryBus()), ZenohTransport(connect), ZenohTransport(connect)
    counters = {"in-process": FrameCounter(), "zenoh": FrameCounter()}
    memory.subscribe(topics.frames(MEM_RUN), counters["in-process"])
    receiver.subscribe(topics.frames(ZENOH_RUN), counters["zenoh"])
    time.sleep(1.0)  # the subscription reaches the publisher through the router
    rounds = []
    try:
        for _ in range(args.rounds):
            pair = []
            for name, bus, run in (("in-process", memory, MEM_RUN), ("zenoh", sender, ZENOH_RUN)):
                stop = threading.Event()

                def blast(bus=bus, run=run, stop=stop) -> None:
                    while not stop.is_set():
                        bus.publish(topics.frames(run, "w0"), payload)

                thread = threading.Thread(target=blast, daemon=True)
                thread.start()
                pair.append(counters[name].rates(args.window)["frames"])
                stop.set()
                thread.join(30)
            rounds.append((pair[0], pair[1]))
    finally:
        sender.close()
        receiver.close()
        router.close()
    return rounds


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--window", type=float, default=10.0, help="seconds each worker is measured per round")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--batch-steps", type=int, default=256)
    p.add_argument("--stride", type=int, default=1, help="keep every n-th pixel (32x32 frames: 1; 16x16: 2)")
    p.add_argument("--capacity", action="store_true", help="also measure what each bus carries without the env")
    args = p.parse_args()
    import torch

    torch.set_num_threads(1)
    side = 32 // args.stride
    print(f"frames/s from one env-worker to a decoding subscriber: chemical-pixels, {side}x{side} RGB frames "
          f"(+ label maps), 4 objects, batches of {args.batch_steps} steps", flush=True)
    alone = core_alone(args)
    print(f"  core alone (no bus), {args.window:.0f} s: {alone['frames']:7,.0f} frames/s "
          f"{alone['bytes'] / 2**20:6.2f} MiB/s", flush=True)
    turns = Turns(args)
    ratios = []
    try:
        turns.wait_started()
        for r in range(args.rounds):
            mem = turns.measure("in-process", 3.0, args.window)
            zen = turns.measure("zenoh", 3.0, args.window)
            ratios.append(zen["frames"] / mem["frames"])
            print(f"  round {r}: in-process {mem['frames']:7,.0f} frames/s {mem['bytes'] / 2**20:6.2f} MiB/s | "
                  f"Zenoh {zen['frames']:7,.0f} frames/s {zen['bytes'] / 2**20:6.2f} MiB/s | ratio {ratios[-1]:.2f}",
                  flush=True)
    finally:
        turns.close()
    print(f"  ratio Zenoh / in-process, median of {len(ratios)} rounds: {statistics.median(ratios):.2f}  (goal >= 0.9)")
    if args.capacity:
        print("what each bus carries without the env (one FrameBatch published back to back, decoded):")
        ratios = []
        for r, (mem, zen) in enumerate(capacity(args)):
            ratios.append(zen / mem)
            print(f"  round {r}: in-process {mem:8,.0f} frames/s | Zenoh {zen:8,.0f} frames/s | ratio {ratios[-1]:.2f}")
        print(f"  ratio Zenoh / in-process, median of {len(ratios)} rounds: {statistics.median(ratios):.2f}")


if __name__ == "__main__":
    main()
