"""factor-extractor service shell: the only factor-extractor file that touches the bus.

Subscribes to ``frames/*``, asks the env-workers' spec on ``env/frames``, learns the slots from the first
frames, then serves the slot factors' spec on ``env/spec`` (what the dynamics-learner and the evaluator
wait for, so they start once the slots are frozen) and publishes each FrameBatch as a TransitionBatch
on ``transitions/<worker>``: the consumers take them unchanged.
"""
from __future__ import annotations

import logging
import sys
import time

from proto import topics
from proto.codec import ProtocolError, decode
from proto.messages import EnvSpec, FrameBatch
from services.bus.base import Transport
from services.factor_extractor.config import FactorExtractorConfig
from services.factor_extractor.core import FactorExtractorCore
from services.runtime.shell import ServiceShell, service_main

SERVICE = "factor-extractor"
log = logging.getLogger(SERVICE)


class _Metrics:
    def __init__(self, shell: ServiceShell) -> None:
        m = shell.metrics
        self.updates = m.counter("causeway_slot_updates", "Updates of the slot representation (autoencoder, then eq. 7.1)")
        self.loss = m.gauge("causeway_slot_loss", "Loss of the last slot update, by term", ("term",))
        self.ready = m.gauge("causeway_slots_frozen_ratio", "1 once the slots are frozen and transitions are published")
        self.frames = m.counter("causeway_frames_received", "Frames received (every distinct frame of every FrameBatch)")
        self.steps = m.counter("causeway_slot_transitions_published", "Transitions of slot factors published")
        self.sent = m.counter("causeway_slot_transition_bytes_published", "Bytes of slot TransitionBatches published")
        self.encode_seconds = m.histogram("causeway_encode_seconds", "Time to turn one FrameBatch into slots",
                                          (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0))
        self.checkpoints = m.counter("causeway_checkpoints", "Checkpoints written")
        self.identity = m.gauge("causeway_slot_identity_ratio", "Share of slots the identity head gives the object "
                                "their mask holds: on its held-out frames, and over the published frames", ("scope",))


def run(cfg: FactorExtractorConfig, transport: Transport | None = None) -> None:
    shell = ServiceShell(SERVICE, cfg, transport)
    metrics = _Metrics(shell)
    frames = shell.inbox("frames", FrameBatch, maxsize=64)
    shell.subscribe(topics.frames(cfg.run_id), frames)
    latest_spec = shell.transport.serve_latest(topics.env_spec(cfg.run_id))
    env = _wait_for_frames_spec(shell)
    if env is None:
        latest_spec.close()
        shell.close()
        return
    core = FactorExtractorCore(cfg, env)
    ckpt = shell.resume(core)
    served = False
    last_ckpt = time.monotonic()
    try:
        while not shell.stopping.is_set():
            shell.poll_control()
            if shell.paused:
                time.sleep(0.02)
                continue
            item = frames.get(timeout=0.0 if core.may_update else 0.05)
            if item is not None:
                _ingest(shell, core, item[1], metrics)
            if core.may_update:
                _train(core, metrics)
            if core.ready and not served:
                shell.set_latest(latest_spec, core.spec())
                served = True
                log.info("slots frozen after %d updates: publishing slot transitions%s", core.learner.updates,
                         _identity_line(core.matching()))
                if (warning := core.binding_warning()) is not None:
                    log.warning(warning)
            metrics.ready.set(float(core.ready))
            _set_identity(metrics, core.matching())
            now = time.monotonic()
            if shell.checkpoint_requested or now - last_ckpt >= cfg.checkpoint_every_s:
                core.checkpoint(ckpt)
                metrics.checkpoints.inc()
                shell.checkpoint_requested, last_ckpt = False, now
            shell.beat(core.progress())
    finally:
        core.checkpoint(ckpt)
        shell.beat(core.progress(), force=True)
        latest_spec.close()
        shell.close()


def _set_identity(metrics: _Metrics, matching: dict[str, float]) -> None:
    for scope, key in (("held_out", "identity_slot_accuracy"), ("published", "published_identity_slot_accuracy")):
        if key in matching:
            metrics.identity.labels(scope=scope).set(matching[key])


def _identity_line(matching: dict[str, float]) -> str:
    if "identity_slot_accuracy" not in matching:
        return " (slot attention's own order)"
    return (f" in object order (identity head, held-out frames: {matching['identity_slot_accuracy']:.3f} of slots, "
            f"{matching['identity_frame_accuracy']:.3f} of frames matched; FG-ARI {matching.get('fg_ari', float('nan')):.3f})")


def _wait_for_frames_spec(shell: ServiceShell, poll_s: float = 0.5) -> EnvSpec | None:
    """Query the frame-publishing env-workers' EnvSpec until one answers (None if stopped first)."""
    while not shell.stopping.is_set():
        for key, payload in shell.transport.query(topics.frames_spec(shell.cfg.run_id), timeout=poll_s):
            try:
                return decode(payload, EnvSpec)
            except ProtocolError as exc:
                shell.metrics.reject(exc.reason)
                log.warning("rejected EnvSpec from %s: %s", key, exc)
        shell.stopping.wait(poll_s)
    return None


def _ingest(shell: ServiceShell, core: FactorExtractorCore, batch: FrameBatch, metrics: _Metrics) -> None:
    t0 = time.perf_counter()
    out = shell.guarded(core.ingest, batch)
    metrics.frames.inc(len(batch.frames))
    if out is None:
        return
    metrics.encode_seconds.observe(time.perf_counter() - t0)
    metrics.sent.inc(shell.publish(topics.transitions(shell.cfg.run_id, out.worker_id), out))
    metrics.steps.inc(len(out))


def _train(core: FactorExtractorCore, metrics: _Metrics) -> None:
    stats = core.train_step()
    metrics.updates.inc()
    for term, value in stats.items():
        if term != "phase":
            metrics.loss.labels(term=term).set(value)


def main(argv: list[str] | None = None) -> None:
    service_main(SERVICE, FactorExtractorConfig, run, argv)


if __name__ == "__main__":
    main(sys.argv[1:])
