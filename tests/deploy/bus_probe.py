"""Small Zenoh programs the multi-host tests run inside network namespaces (``ip netns exec``).

    python -m tests.deploy.bus_probe router  --listen E [--listen E2] [--connect E] [--config FILE]
    python -m tests.deploy.bus_probe publish --connect E --run R --worker W --rate B --seconds S [BUS]
    python -m tests.deploy.bus_probe count   --connect E --run R --seconds S [BUS]
    python -m tests.deploy.bus_probe open    --connect E [BUS]
    python -m tests.deploy.bus_probe put     --connect E --key K --payload P --seconds S [BUS]
    python -m tests.deploy.bus_probe watch   --connect E --key K --seconds S [BUS]

``BUS`` is ``--credentials FILE`` (a role's ``user:password`` file) and ``--root-ca FILE`` (the CA of a
``tls/`` router), both optional. ``--config`` runs a router from a configuration file (``causeway
bus-secrets``' ``router.json5``, without its plugins) instead of an open one; ``--listen`` then
replaces its endpoints. ``open`` tries to open a session and says whether it did; ``put`` publishes
``P`` on ``K`` ten times a second; ``watch`` counts what arrives on ``K`` by payload.

``router`` runs a Zenoh router (the Python session, as ``services.bus.router``; ``--connect`` meshes it
with another router) until SIGTERM. ``publish`` sends real ``TransitionBatch`` messages (256 steps of
Chemical's size, consecutive ``seq``) on ``transitions/<W>`` at ``B`` batches/s (0: as fast as the bus
takes them), BLOCK congestion control like the env-workers. ``count`` subscribes to every worker's
transitions and prints, per worker, the batches and steps received, the ``seq`` gaps (batches lost)
and the arrival times, as one JSON line. Every program stops by itself after ``--seconds``.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from typing import Sequence

import numpy as np

from proto import topics
from proto.codec import decode, encode
from proto.messages import TransitionBatch
from services.bus.credentials import Credentials, read_credentials
from services.bus.router import client_config, router_config, wait_for_router
from services.bus.zenoh_transport import ZenohTransport

STEPS = 256
STATE_DIM = 30
"""Chemical with 10 objects: 10 colours one-hot over 3 values."""
LINGER_S = 2.0
"""A publisher waits this long before closing its session, so what it queued has left it."""


def batch(worker: str, seq: int) -> TransitionBatch:
    rng = np.random.default_rng(seq)
    state = rng.random((STEPS, STATE_DIM), dtype=np.float32)
    return TransitionBatch(worker_id=worker, seq=seq, policy_version=0, state=state,
                           action=rng.integers(0, 30, (STEPS, 1)).astype(np.float32),
                           reward=np.zeros(STEPS, np.float32), next_state=state[::-1].copy(),
                           terminated=np.zeros(STEPS, bool), truncated=np.zeros(STEPS, bool),
                           episode_id=np.full(STEPS, seq // 4, np.int64), step=np.arange(STEPS, dtype=np.int32))


def run_router(listen: Sequence[str], connect: Sequence[str], config_file: str = "") -> None:
    import zenoh

    if config_file:
        config = zenoh.Config.from_file(config_file)
        config.insert_json5("plugins", "{}")
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("scouting/delay", "0")
    else:
        config = router_config(listen[0])
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM, signal.SIGINT})
    session = zenoh.open(config)
    print(json.dumps({"router": str(session.zid()), "listen": list(listen), "connect": list(connect)}), flush=True)
    signal.sigwait({signal.SIGTERM, signal.SIGINT})
    session.close()


def _bus(connect: str, credentials: Credentials | None, root_ca: str) -> ZenohTransport:
    """A client of ``connect`` once the router answers (a plain one is probed on its own endpoint)."""
    if not root_ca:
        wait_for_router(connect, timeout=60, credentials=credentials)
    return ZenohTransport(connect, credentials, root_ca)


def run_publish(connect: str, run: str, worker: str, rate: float, seconds: float,
                credentials: Credentials | None = None, root_ca: str = "") -> dict:
    bus = _bus(connect, credentials, root_ca)
    sent, started = 0, time.monotonic()
    try:
        while time.monotonic() - started < seconds:
            bus.publish(topics.transitions(run, worker), encode(batch(worker, sent)), reliable=True)
            sent += 1
            if rate > 0:
                time.sleep(max(0.0, started + sent / rate - time.monotonic()))
    finally:
        elapsed = time.monotonic() - started
        time.sleep(LINGER_S)
        bus.close()
    return {"worker": worker, "sent": sent, "seconds": round(elapsed, 3)}


def run_count(connect: str, run: str, seconds: float, credentials: Credentials | None = None,
              root_ca: str = "") -> dict:
    lock = threading.Lock()
    seen: dict[str, dict] = {}
    started = time.time()

    def on_payload(key: str, payload: bytes) -> None:
        message = decode(payload, TransitionBatch)
        with lock:
            entry = seen.setdefault(message.worker_id, {"batches": 0, "steps": 0, "seqs": [], "arrivals": []})
            entry["batches"] += 1
            entry["steps"] += len(message)
            entry["seqs"].append(message.seq)
            entry["arrivals"].append(round(time.time() - started, 3))

    bus = _bus(connect, credentials, root_ca)
    handle = bus.subscribe(topics.transitions(run), on_payload)
    time.sleep(seconds)
    handle.close()
    bus.close()
    with lock:
        return {"started": started, "workers": {w: _summary(e) for w, e in seen.items()}}


def run_open(connect: str, credentials: Credentials | None, root_ca: str) -> dict:
    import zenoh

    config = client_config(connect, credentials, root_ca)
    config.insert_json5("connect/timeout_ms", "5000")
    try:
        zenoh.open(config).close()
    except zenoh.ZError as error:
        return {"opened": False, "error": str(error)[:300]}
    return {"opened": True, "error": ""}


def run_put(connect: str, key: str, payload: str, seconds: float, credentials: Credentials | None,
            root_ca: str) -> dict:
    bus = _bus(connect, credentials, root_ca)
    sent, started = 0, time.monotonic()
    while time.monotonic() - started < seconds:
        bus.publish(key, payload.encode(), reliable=True)
        sent += 1
        time.sleep(0.1)
    time.sleep(LINGER_S)
    bus.close()
    return {"sent": sent}


def run_watch(connect: str, key: str, seconds: float, credentials: Credentials | None, root_ca: str) -> dict:
    lock = threading.Lock()
    payloads: dict[str, int] = {}

    def on_payload(_: str, payload: bytes) -> None:
        with lock:
            text = payload.decode(errors="replace")
            payloads[text] = payloads.get(text, 0) + 1

    bus = _bus(connect, credentials, root_ca)
    handle = bus.subscribe(key, on_payload)
    print(json.dumps({"watching": key}), flush=True)
    time.sleep(seconds)
    handle.close()
    bus.close()
    with lock:
        return {"payloads": payloads}


def _summary(entry: dict) -> dict:
    seqs = sorted(entry["seqs"])
    expected = seqs[-1] - seqs[0] + 1 if seqs else 0
    return {"batches": entry["batches"], "steps": entry["steps"], "first_seq": seqs[0] if seqs else None,
            "last_seq": seqs[-1] if seqs else None, "lost": expected - len(set(seqs)),
            "duplicates": len(seqs) - len(set(seqs)), "arrivals": entry["arrivals"], "seqs": entry["seqs"]}


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="bus_probe")
    sub = parser.add_subparsers(dest="program", required=True)
    router = sub.add_parser("router")
    router.add_argument("--listen", action="append", required=True)
    router.add_argument("--connect", action="append", default=[])
    router.add_argument("--config", default="")
    for name in ("publish", "count", "open", "put", "watch"):
        p = sub.add_parser(name)
        p.add_argument("--connect", required=True)
        p.add_argument("--credentials", default="")
        p.add_argument("--root-ca", default="")
        if name in ("publish", "count"):
            p.add_argument("--run", required=True)
        if name != "open":
            p.add_argument("--seconds", type=float, required=True)
        if name == "publish":
            p.add_argument("--worker", required=True)
            p.add_argument("--rate", type=float, default=0.0)
        if name in ("put", "watch"):
            p.add_argument("--key", required=True)
        if name == "put":
            p.add_argument("--payload", required=True)
    args = parser.parse_args(argv)
    if args.program == "router":
        run_router(args.listen, args.connect, args.config)
        return
    bus = (args.connect, read_credentials(args.credentials) if args.credentials else None, args.root_ca)
    if args.program == "publish":
        result = run_publish(args.connect, args.run, args.worker, args.rate, args.seconds, *bus[1:])
    elif args.program == "count":
        result = run_count(args.connect, args.run, args.seconds, *bus[1:])
    elif args.program == "open":
        result = run_open(*bus)
    elif args.program == "put":
        result = run_put(args.connect, args.key, args.payload, args.seconds, *bus[1:])
    else:
        result = run_watch(args.connect, args.key, args.seconds, *bus[1:])
    sys.stdout.write(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()
