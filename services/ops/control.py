"""``causeway scale | stop | checkpoint``: Control messages to a running stack.

    causeway scale env-worker N (--run RUN [--connect E] | --run-dir runs/X) [--timeout-s 10]
    causeway scale env-worker N --compose-project P [--docker-host URL]
    causeway stop (--run RUN [--connect E] | --run-dir runs/X) [--timeout-s 30]
    causeway checkpoint (--run RUN [--connect E] | --run-dir runs/X)

``scale`` asks the local supervisor (``control/supervisor``, argument ``env-worker=N``) and waits
until N env-worker tokens are alive; under Compose it changes the containers instead
(``compose_scale``). ``stop`` and ``checkpoint`` go to ``control/all``: every service and the
supervisor receive them. Exit 0 when the effect was seen, 1 when it was not seen in time, 2 when
the router (or Docker engine) could not be reached or the request is invalid.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence, TextIO

from proto import topics
from proto.codec import encode
from proto.messages import Control
from services.bus.base import Transport
from services.ops.observe import Instance, RunObserver
from services.ops.target import (EXIT_NOT_CONFIRMED, OpsError, Target, add_target_arguments, check_scalable,
                                 open_bus, resolve_target, run_dir_config)

SETTLE_S = 3.0
"""How long a new watcher may take to report the tokens alive now (only a loaded machine needs long)."""
QUERY_S = 5.0
"""Limit of a liveliness query; it returns as soon as the router has answered, this only bounds a stall."""


def send(bus: Transport, run_id: str, to: str, command: str, argument: str = "") -> None:
    """Publish one Control message on ``control/<to>`` of the run."""
    message = Control(command=command, argument=argument, issued_at=time.time())
    bus.publish(topics.control(run_id, to), encode(message), reliable=True)


def names(instances: Sequence[Instance]) -> str:
    return ", ".join(f"{service}/{instance}" for service, instance in instances) or "none"


def alive_now(bus: Transport, run_id: str, service: str = "*") -> list[Instance]:
    """(service, instance) of every token of the run (of ``service``) alive now, by one liveliness query."""
    return sorted({topics.parse_alive(k)[1:] for k in bus.alive(topics.alive(run_id, service), timeout=QUERY_S)})


def settled_observer(bus: Transport, run_id: str, service: str = "*") -> tuple[RunObserver, list[Instance]]:
    """A token watcher that has reported at least the tokens alive now, and those tokens.

    The query goes first: with eclipse-zenoh 1.10.2, a liveliness query issued within ~0.2 s of the
    same session declaring an intersecting liveliness subscriber finds nothing (20 misses in 20
    against a live stack; none when the query comes first or 0.2 s later).
    """
    expected = set(alive_now(bus, run_id, service))
    observer = RunObserver(bus, run_id, service, beats=False)
    observer.wait_until(lambda o: expected <= set(o.alive()), SETTLE_S)
    return observer, observer.alive()


def scale_local(bus: Transport, run_id: str, service: str, count: int, timeout_s: float, out: TextIO) -> int:
    """Ask the supervisor for ``count`` instances of ``service``; wait until that many tokens are alive."""
    observer, before = settled_observer(bus, run_id, service)
    with observer:
        out.write(f"{service}: {len(before)} alive ({names(before)}); asking the supervisor for {count}\n")
        send(bus, run_id, "supervisor", "scale", f"{service}={count}")
        started = time.monotonic()
        done = observer.wait_until(lambda o: len(o.alive(service)) == count, timeout_s)
        after = observer.alive()
    elapsed = time.monotonic() - started
    if not done:
        raise OpsError(f"{service}: still {len(after)} alive ({names(after)}) after {timeout_s:.0f}s; is the "
                       f"run's supervisor up? (a compose stack scales with --compose-project)", EXIT_NOT_CONFIRMED)
    added, gone = sorted(set(after) - set(before)), sorted(set(before) - set(after))
    out.write(f"{service}: {len(before)} -> {len(after)} alive in {elapsed:.1f}s"
              f" (started: {names(added)}; stopped: {names(gone)})\n")
    return 0


def stop(bus: Transport, run_id: str, timeout_s: float, out: TextIO) -> int:
    """Broadcast stop; wait until no token of the run is left."""
    observer, before = settled_observer(bus, run_id)
    with observer:
        send(bus, run_id, "all", "stop")
        out.write(f"stop sent to run {run_id}; alive: {names(before)}\n")
        done = observer.wait_until(lambda o: not o.alive(), timeout_s)
        left = observer.alive()
    if not done:
        raise OpsError(f"still alive after {timeout_s:.0f}s: {names(left)}", EXIT_NOT_CONFIRMED)
    out.write(f"stopped: {names(before)}\n")
    return 0


def checkpoint(bus: Transport, run_id: str, out: TextIO) -> int:
    """Broadcast checkpoint; report who was alive to receive it (exit 1 when nobody was)."""
    alive = alive_now(bus, run_id)
    send(bus, run_id, "all", "checkpoint")
    out.write(f"checkpoint sent to run {run_id}; alive to receive it: {names(alive)}\n")
    return 0 if alive else EXIT_NOT_CONFIRMED


def _parser(prog: str, description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"causeway {prog}", description=description)
    add_target_arguments(p)
    return p


def scale_main(argv: Sequence[str], out: TextIO | None = None) -> int:
    p = _parser("scale", "Change the number of env-worker instances of a running stack, without a restart.")
    p.add_argument("service", help="the service to scale: env-worker")
    p.add_argument("count", type=int, help="how many instances to run")
    p.add_argument("--timeout-s", type=float, default=10.0, help="seconds to wait for the tokens (default 10)")
    p.add_argument("--compose-project", default=None, help="scale the containers of this Docker Compose project")
    p.add_argument("--docker-host", default=None, help="Docker engine URL (default: $DOCKER_HOST or the local socket)")
    args = p.parse_args(list(argv))
    out = out or sys.stdout
    check_scalable(args.service, args.count)
    if args.compose_project:
        from services.ops import compose_scale  # the Docker SDK, only when it is needed

        return compose_scale.main(args.compose_project, args.service, args.count, args.docker_host, out)
    target = resolve_target(args)
    limit = run_dir_config(Path(args.run_dir)).get("max_workers") if args.run_dir else None
    if isinstance(limit, int) and args.count > limit:
        raise OpsError(f"the run allows at most {limit} {args.service} instances (--max-workers); its supervisor "
                       f"would refuse {args.count}")
    with open_bus(target) as bus:
        return scale_local(bus, target.run_id, args.service, args.count, args.timeout_s, out)


def stop_main(argv: Sequence[str], out: TextIO | None = None) -> int:
    p = _parser("stop", "Stop every service of a run and its supervisor (which writes summary.json). Under "
                        "Compose, Docker's restart policy (unless-stopped) starts the containers again: use make down.")
    p.add_argument("--timeout-s", type=float, default=30.0, help="seconds to wait for every token to go (default 30)")
    args = p.parse_args(list(argv))
    target = resolve_target(args)
    with open_bus(target) as bus:
        return stop(bus, target.run_id, args.timeout_s, out or sys.stdout)


def checkpoint_main(argv: Sequence[str], out: TextIO | None = None) -> int:
    args = _parser("checkpoint", "Ask every service of a run to write its checkpoint now.").parse_args(list(argv))
    target: Target = resolve_target(args)
    with open_bus(target) as bus:
        return checkpoint(bus, target.run_id, out or sys.stdout)
