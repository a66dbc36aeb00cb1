"""env-worker service shell: the only env-worker file that touches the bus."""
from __future__ import annotations

import logging
import sys
import time

from proto import topics
from proto.codec import encode
from services.bus.base import Transport
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.runtime.config import parse_config
from services.runtime.shell import ServiceShell, setup_logging

SERVICE = "env-worker"
log = logging.getLogger(SERVICE)


def run(cfg: EnvWorkerConfig, transport: Transport | None = None) -> None:
    """Publish the EnvSpec (also to late queries), then transition batches until stopped."""
    core = EnvWorkerCore(cfg)
    cfg = core.cfg
    shell = ServiceShell(SERVICE, cfg, transport)
    steps = shell.metrics.counter("causeway_env_steps", "Environment steps taken")
    episodes = shell.metrics.counter("causeway_env_episodes", "Episodes finished")
    batches = shell.metrics.counter("causeway_transition_batches_published", "TransitionBatches published")
    sent = shell.metrics.counter("causeway_transition_bytes_published", "Bytes of TransitionBatches published")
    publish_seconds = shell.metrics.histogram("causeway_publish_seconds", "Time to publish one batch",
                                              (0.0005, 0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1.0))
    spec_value = shell.transport.serve_latest(topics.env_spec(cfg.run_id))
    spec_value.set(encode(core.spec))
    key = topics.transitions(cfg.run_id, core.worker_id)
    started, last_episode = time.monotonic(), 0
    try:
        while not shell.stopping.is_set():
            shell.poll_control()
            if shell.paused:
                time.sleep(0.05)
                continue
            batch = core.collect()
            t0 = time.perf_counter()
            sent.inc(shell.publish(key, batch))
            publish_seconds.observe(time.perf_counter() - t0)
            steps.inc(len(batch))
            batches.inc()
            episodes.inc(core.episode - last_episode)
            last_episode = core.episode
            shell.beat({"env_steps": core.env_steps, "episodes": core.episode})
            if cfg.max_steps and core.env_steps >= cfg.max_steps:
                break
            _throttle(cfg.max_steps_per_second, core.env_steps, started)
    finally:
        shell.beat({"env_steps": core.env_steps, "episodes": core.episode}, force=True)
        spec_value.close()
        shell.close()


def _throttle(rate: float, done: int, started: float) -> None:
    if rate > 0:
        ahead = done / rate - (time.monotonic() - started)
        if ahead > 0:
            time.sleep(ahead)


def main(argv: list[str] | None = None) -> None:
    setup_logging(SERVICE)
    cfg = parse_config(EnvWorkerConfig, argv)
    log.info("starting worker %d on %s", cfg.worker_index, cfg.env)
    run(cfg)


if __name__ == "__main__":
    main(sys.argv[1:])
