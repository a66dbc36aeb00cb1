"""env-worker service shell: the only env-worker file that touches the bus."""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import numpy as np

from proto import topics
from proto.codec import encode
from proto.messages import Weights
from services.bus.base import Transport
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore, next_generation, resolve_worker_index
from services.runtime.shell import Inbox, ServiceShell, parse_service_config, setup_logging

SERVICE = "env-worker"
log = logging.getLogger(SERVICE)


def run(cfg: EnvWorkerConfig, transport: Transport | None = None) -> None:
    """Publish the EnvSpec (also to late queries), then transition batches until stopped."""
    cfg = resolve_worker_index(cfg)
    generation = next_generation(Path(cfg.run_dir) / "checkpoints" / f"{SERVICE}-{cfg.instance}.json")
    core = EnvWorkerCore(cfg, generation)
    cfg = core.cfg
    if cfg.follow_policy or cfg.skild:
        import torch

        from causal.rl.policy_weights import warm_up

        torch.set_num_threads(1)
        warm_up()  # before going live, so loading the first policy never waits for imports
    shell = ServiceShell(SERVICE, cfg, transport)
    steps = shell.metrics.counter("causeway_env_steps", "Environment steps taken")
    episodes = shell.metrics.counter("causeway_env_episodes", "Episodes finished")
    batches = shell.metrics.counter("causeway_transition_batches_published", "TransitionBatches published")
    sent = shell.metrics.counter("causeway_transition_bytes_published",
                                 "Bytes of TransitionBatches (and FrameBatches: --publish-frames, --frames-beside) published")
    options = shell.metrics.counter("causeway_skill_options_chosen",
                                    "Skills started by a collection policy over skills, by option and policy "
                                    "(uniform: the chapter's Uniform skills; learned: published policy weights)",
                                    ("option", "policy"))
    chosen: dict[str, int] = {}
    publish_seconds = shell.metrics.histogram("causeway_publish_seconds", "Time to publish one batch",
                                              (0.0005, 0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1.0))
    # With frames, env/spec is the factor-extractor's (slot factors); the env's own spec is env/frames.
    spec_key = topics.frames_spec(cfg.run_id) if cfg.publish_frames else topics.env_spec(cfg.run_id)
    spec_value = shell.transport.serve_latest(spec_key)
    spec_value.set(encode(core.spec))
    follower = _PolicyFollower(shell, core, cfg) if cfg.follow_policy or cfg.skild else None
    if cfg.publish_frames:
        topic, collect = topics.frames(cfg.run_id, core.worker_id), core.collect_frames
    else:
        topic, collect = topics.transitions(cfg.run_id, core.worker_id), core.collect
    started, last_episode = time.monotonic(), 0
    try:
        while not shell.stopping.is_set():
            shell.poll_control()
            if shell.paused:
                time.sleep(0.05)
                continue
            if follower is not None:
                follower.update()
            if core.waiting:  # SkiLD: every step is a skill's
                time.sleep(0.05)
                continue
            batch = collect()
            t0 = time.perf_counter()
            sent.inc(shell.publish(topic, batch))
            if cfg.frames_beside:
                sent.inc(shell.publish(topics.frames(cfg.run_id, core.worker_id), core.frames_of(batch)))
            if core.skild is not None:
                sent.inc(shell.publish(topics.skills(cfg.run_id, core.worker_id), core.skill_batch(batch)))
            publish_seconds.observe(time.perf_counter() - t0)
            steps.inc(len(batch))
            batches.inc()
            episodes.inc(core.episode - last_episode)
            last_episode = core.episode
            for (option, policy), n in option_counts(batch, core.option_names).items():
                options.labels(option=option, policy=policy).inc(n)
                stat = f"options_{policy}_{option}"
                chosen[stat] = chosen.get(stat, 0) + n
            shell.beat({"env_steps": core.env_steps, "episodes": core.episodes_finished, "policy_version": batch.policy_version,
                        **core.episodes.values(), **chosen})
            if cfg.max_steps and core.env_steps >= cfg.max_steps:
                break
            _throttle(cfg.max_steps_per_second, core.env_steps, started)
    finally:
        shell.beat({"env_steps": core.env_steps, "episodes": core.episodes_finished, "policy_version": core.policy.version,
                    **core.episodes.values(), **chosen}, force=True)
        spec_value.close()
        shell.close()


class _PolicyFollower:
    """Keeps the worker's actor on the newest policy: the published stream, a query at start (a late
    worker catches up at once) and a query every ``policy_poll_s`` (a missed publication is caught).
    The version in use is exported, so a worker left behind is visible."""

    def __init__(self, shell: ServiceShell, core: EnvWorkerCore, cfg: EnvWorkerConfig) -> None:
        from causal.rl.policy_weights import MODEL
        from causal.skild_policy import MODEL as SKILD_MODEL

        self.shell, self.core, self.cfg = shell, core, cfg
        self.key = topics.weights(cfg.run_id, SKILD_MODEL if cfg.skild else MODEL)
        self.inbox: Inbox = shell.inbox("policy", Weights, maxsize=4)
        shell.subscribe(self.key, self.inbox)
        m = shell.metrics
        self.in_use = m.gauge("causeway_policy_version_in_use", "Version of the policy weights this worker acts with")
        self.loaded = m.counter("causeway_policy_weights_loaded", "Policy weights loaded by this worker")
        self.skipped = m.counter("causeway_policy_versions_skipped",
                                 "Versions superseded before this worker loaded them (newer ones arrived first)")
        self.last_query = 0.0

    def update(self) -> None:
        candidates = [w for _, w in self.inbox.drain()]
        now = time.monotonic()
        if now - self.last_query >= self.cfg.policy_poll_s:
            candidates += self._query()
            self.last_query = now
        if candidates:
            self._load(max(candidates, key=lambda w: w.version))

    def _query(self) -> list[Weights]:
        return self.shell.query(self.key, Weights)

    def _load(self, weights: Weights) -> None:
        before = self.core.policy.version
        try:
            if not self.core.apply_weights(weights):
                return
        except ValueError as exc:
            self.shell.metrics.reject("inconsistent")
            log.warning("rejected policy v%d: %s", weights.version, exc)
            return
        self.loaded.inc()
        if before:
            self.skipped.inc(max(weights.version - before - 1, 0))
        else:
            log.info("acting with policy v%d from now on", weights.version)
        self.in_use.set(weights.version)


def option_counts(batch, names: tuple[str, ...]) -> dict[tuple[str, str], int]:
    """Skills started in ``batch`` by (option name of ``names``, ``uniform`` or ``learned``); {} without options."""
    option = getattr(batch, "option", None)  # a FrameBatch carries none
    if option is None or not names:
        return {}
    counts = np.bincount(option[option >= 0], minlength=len(names))
    policy = "learned" if batch.policy_version > 0 else "uniform"
    return {(names[i], policy): int(n) for i, n in enumerate(counts) if n}


def _throttle(rate: float, done: int, started: float) -> None:
    if rate > 0:
        ahead = done / rate - (time.monotonic() - started)
        if ahead > 0:
            time.sleep(ahead)


def main(argv: list[str] | None = None) -> None:
    setup_logging(SERVICE)
    cfg = parse_service_config(EnvWorkerConfig, argv)
    log.info("starting worker %d on %s", cfg.worker_index, cfg.env)
    run(cfg)


if __name__ == "__main__":
    main(sys.argv[1:])
