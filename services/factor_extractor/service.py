"""factor-extractor service shell: the only factor-extractor file that touches the bus.

Mode ``slots`` (Dyn-O, ch. 7): subscribes to ``frames/*``, asks the env-workers' spec on ``env/frames``,
learns the slots from the first frames, then serves the slot factors' spec on ``env/spec`` (what the
dynamics-learner and the evaluator wait for, so they start once the slots are frozen) and publishes each
FrameBatch as a TransitionBatch on ``transitions/<worker>``: the consumers take them unchanged.

Mode ``latent-actions`` (FLAM, ch. 8): the env-workers publish transitions and frames; the extractor
asks the env's spec on ``env/spec``, takes the learner's FLAM weights (``weights/<method>``, queried once
at start as a late joiner does) and publishes each FrameBatch's per-slot latent actions on
``latent/<worker>`` (:mod:`services.factor_extractor.latent`).
"""
from __future__ import annotations

import logging
import sys
import time

from proto import topics
from proto.messages import FrameBatch, Weights
from services.bus.base import Transport
from services.factor_extractor.config import FactorExtractorConfig
from services.factor_extractor.core import FactorExtractorCore
from services.factor_extractor.latent import LatentActionLabeller
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
    if cfg.mode == "latent-actions":
        run_labeller(cfg, transport)
        return
    shell = ServiceShell(SERVICE, cfg, transport)
    metrics = _Metrics(shell)
    frames = shell.inbox("frames", FrameBatch, maxsize=64)
    shell.subscribe(topics.frames(cfg.run_id), frames)
    latest_spec = shell.transport.serve_latest(topics.env_spec(cfg.run_id))
    env = shell.wait_for_spec(key=topics.frames_spec(cfg.run_id))
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
            last_ckpt = shell.checkpoint_if_due(core, ckpt, last_ckpt, metrics.checkpoints)
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


class _LabelMetrics:
    def __init__(self, shell: ServiceShell) -> None:
        m = shell.metrics
        self.frames = m.counter("causeway_frames_received", "Frames received (every distinct frame of every FrameBatch)")
        self.labelled = m.counter("causeway_latent_action_steps_labelled", "Steps labelled with per-slot latent actions")
        self.unlabelled = m.counter("causeway_latent_action_steps_unlabelled",
                                    "Steps received before FLAM weights past the autoencoder phase were held")
        self.sent = m.counter("causeway_latent_action_bytes_published", "Bytes of LatentActions published")
        self.version = m.gauge("causeway_latent_action_weights_version", "Version of the FLAM weights labelling")
        self.kl = m.gauge("causeway_latent_action_kl", "Each slot's mean KL to N(0, I) over the newest labelled "
                          "batches (nats per transition: what its latent action carries)", ("slot",))
        self.label_seconds = m.histogram("causeway_label_seconds", "Time to label one FrameBatch",
                                         (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0))
        self.checkpoints = m.counter("causeway_checkpoints", "Checkpoints written")


def run_labeller(cfg: FactorExtractorConfig, transport: Transport | None = None) -> None:
    """Mode ``latent-actions``: label every FrameBatch with the newest FLAM weights' per-slot latent actions."""
    shell = ServiceShell(SERVICE, cfg, transport)
    metrics = _LabelMetrics(shell)
    frames = shell.inbox("frames", FrameBatch, maxsize=64)
    weights = shell.inbox("weights", Weights, maxsize=2)
    shell.subscribe(topics.frames(cfg.run_id), frames)
    shell.subscribe(topics.weights(cfg.run_id, cfg.method), weights)
    env = shell.wait_for_spec()
    if env is None:
        shell.close()
        return
    core = LatentActionLabeller(cfg, env)
    ckpt = shell.resume(core)
    _load_weights(shell, core, shell.query(topics.weights(cfg.run_id, cfg.method), Weights), metrics)  # a late joiner
    last_ckpt = time.monotonic()
    try:
        while not shell.stopping.is_set():
            shell.poll_control()
            _load_weights(shell, core, [w for _, w in weights.drain()], metrics)
            item = frames.get(timeout=0.05) if not shell.paused else None
            if item is not None:
                _label(shell, core, item[1], metrics)
            last_ckpt = shell.checkpoint_if_due(core, ckpt, last_ckpt, metrics.checkpoints)
            shell.beat(core.progress())
    finally:
        core.checkpoint(ckpt)
        shell.beat(core.progress(), force=True)
        shell.close()


def _load_weights(shell: ServiceShell, core: LatentActionLabeller, weights: list[Weights], metrics: _LabelMetrics) -> None:
    for w in weights:
        try:
            was_ready = core.ready
            if core.load_weights(w) and core.ready and not was_ready:
                log.info("labelling latent actions with FLAM weights v%d (%d updates)", w.version, w.updates)
        except ValueError as exc:  # ProtocolError is one: a version past the bound
            shell.metrics.reject(getattr(exc, "reason", "inconsistent"))
            log.warning("rejected weights v%d: %s", w.version, exc)
    metrics.version.set(core.weights_version)


def _label(shell: ServiceShell, core: LatentActionLabeller, batch: FrameBatch, metrics: _LabelMetrics) -> None:
    t0 = time.perf_counter()
    metrics.frames.inc(len(batch.frames))
    out = shell.guarded(core.label, batch)
    if out is None:
        if not core.ready:
            metrics.unlabelled.inc(len(batch))
        return
    metrics.label_seconds.observe(time.perf_counter() - t0)
    metrics.sent.inc(shell.publish(topics.latent_actions(shell.cfg.run_id, out.worker_id), out))
    metrics.labelled.inc(len(out))
    for k, value in enumerate(core.slot_kl()):
        metrics.kl.labels(slot=str(k)).set(value)


def main(argv: list[str] | None = None) -> None:
    service_main(SERVICE, FactorExtractorConfig, run, argv)


if __name__ == "__main__":
    main(sys.argv[1:])
