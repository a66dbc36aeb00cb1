"""The factor-extractor's latent-action labels (FLAM, ch. 8; issue 25 item 6), core only: a real env-worker
core publishing frames beside its transitions, a real dynamics-learner core training FLAM, and the labeller
taking the learner's weights after the msgpack round trip. A label is the posterior of the step's clip
(s_t, s_{t+1}), the same as the model gives that clip alone; nothing is labelled before the latent-action
phase; weights or frames the model cannot read are refused."""
from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
import pytest
import torch

from causal.flam_nets import gaussian_kl
from proto.codec import ProtocolError, decode, encode
from proto.messages import FrameBatch, LatentActions, ServiceStats, Weights
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.factor_extractor.config import FactorExtractorConfig
from services.factor_extractor.latent import RECENT_BATCHES, LatentActionLabeller
from services.runtime.config import build_config
from services.supervisor.report_slots import label_facts, slot_facts

torch.set_num_threads(1)
FLAM = dict(method="flam", flam_slot_dim=8, flam_action_dim=2, flam_iterations=1, flam_ae_updates=2,
            flam_batch_size=4, flam_live_every=0, warmup_steps=50)


def _worker(**kw) -> EnvWorkerCore:
    return EnvWorkerCore(build_config(EnvWorkerConfig, env="multigrid-agents", batch_steps=48, frames_beside=True, **kw))


def _learner(worker: EnvWorkerCore, updates: int) -> DynamicsLearnerCore:
    core = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **FLAM), worker.spec)
    core.ingest(worker.collect())
    for _ in range(updates):
        core.train_step()
    return core


def _labeller(worker: EnvWorkerCore) -> LatentActionLabeller:
    return LatentActionLabeller(build_config(FactorExtractorConfig, method="flam", mode="latent-actions"), worker.spec)


def _round_trip(core: DynamicsLearnerCore) -> Weights:
    return decode(encode(core.weights()), Weights)


def test_frames_beside_match_the_transitions() -> None:
    worker = _worker()
    batch = worker.collect()
    frames = decode(encode(worker.frames_of(batch)), FrameBatch)
    assert (frames.worker_id, frames.seq, len(frames)) == (batch.worker_id, batch.seq, len(batch))
    render = worker.env.unwrapped
    drawn, _ = render.render_positions(batch.next_state.reshape(len(batch), -1, 2).round().astype(np.int64))
    np.testing.assert_array_equal(frames.frames[frames.next_frame], drawn)
    assert frames.labels is None, "the labeller reads no label maps: frames beside transitions go without them"
    published = EnvWorkerCore(build_config(EnvWorkerConfig, env="multigrid-agents", batch_steps=48, publish_frames=True))
    assert published.frames_of(published.collect()).labels is not None, "the slot extractor's mask prior reads them"
    with pytest.raises(ValueError, match="exclude each other"):
        build_config(EnvWorkerConfig, env="multigrid-agents", frames_beside=True, publish_frames=True)


def test_labels_are_each_steps_clip_posterior_from_the_newest_weights() -> None:
    worker = _worker()
    learner = _learner(worker, updates=2)  # the autoencoder phase only
    batch = worker.collect()
    frames = worker.frames_of(batch)
    labeller = _labeller(worker)
    assert labeller.label(frames) is None and labeller.unlabelled_steps == len(batch)
    assert labeller.load_weights(_round_trip(learner)) and not labeller.ready  # no latent-action update yet
    assert labeller.label(frames) is None
    for _ in range(3):
        learner.train_step()
    weights = _round_trip(learner)
    assert labeller.load_weights(weights) and labeller.ready and not labeller.load_weights(weights)
    out = decode(encode(labeller.label(frames)), LatentActions)
    k, d = learner.trainer.model.lam.config.num_slots, learner.trainer.model.lam.config.action_dim
    assert out.mean.shape == out.log_sigma.shape == (len(batch), k, d)
    assert (out.kind, out.worker_id, out.seq, out.weights_version) == ("flam", batch.worker_id, batch.seq, weights.version)
    np.testing.assert_array_equal(out.episode_id, batch.episode_id)
    np.testing.assert_array_equal(out.step, batch.step)
    model = learner.trainer.model.eval()
    with torch.no_grad():
        for t in (0, 17, len(batch) - 1):
            clip = torch.from_numpy(frames.frames[[frames.state_frame[t], frames.next_frame[t]]])[None]
            mean, log_sigma = model.lam.posterior(model.features(clip))
            np.testing.assert_allclose(out.mean[t], mean[0, 0].numpy(), rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(out.log_sigma[t], log_sigma[0, 0].numpy(), rtol=1e-4, atol=1e-5)
    kl = gaussian_kl(torch.from_numpy(out.mean), torch.from_numpy(out.log_sigma)).double().mean(0).numpy()
    np.testing.assert_allclose(labeller.slot_kl(), kl, rtol=1e-5)
    assert labeller.run_slot_kl() == labeller.slot_kl()  # one batch: the recent window is the run
    progress = labeller.progress()
    assert progress["labelled_steps"] == len(batch) and progress["labels_weights_version"] == weights.version
    assert [progress[f"stream_slot{i}_kl"] for i in range(k)] == labeller.slot_kl()
    beat = ServiceStats("factor-extractor", "0", {key: float(value) for key, value in progress.items()})
    facts = label_facts(beat)["latent_labels"]
    assert (facts["labelled_steps"], facts["unlabelled_steps"], facts["weights_version"]) == (48, 96, weights.version)
    np.testing.assert_allclose(facts["slot_kl"], kl, rtol=1e-5)
    np.testing.assert_allclose(facts["run_slot_kl"], kl, rtol=1e-5)
    assert slot_facts(beat) == {}  # the slots block is the other mode's


def test_the_recent_kl_follows_the_newest_batches_and_the_runs_keeps_them_all() -> None:
    worker = _worker()
    learner = _learner(worker, updates=3)
    labeller = _labeller(worker)
    labeller.load_weights(_round_trip(learner))
    labeller.recent = deque(maxlen=1)  # a window of one batch (RECENT_BATCHES in a run)
    per_batch = []
    for _ in range(2):
        out = labeller.label(worker.frames_of(worker.collect()))
        per_batch.append(gaussian_kl(torch.from_numpy(out.mean), torch.from_numpy(out.log_sigma)).double().mean(0).numpy())
        for _ in range(20):  # the next batch is labelled by newer weights
            learner.train_step()
        labeller.load_weights(_round_trip(learner))
    assert RECENT_BATCHES >= 16
    np.testing.assert_allclose(labeller.slot_kl(), per_batch[1], rtol=1e-5)
    np.testing.assert_allclose(labeller.run_slot_kl(), (per_batch[0] + per_batch[1]) / 2, rtol=1e-5)
    assert np.abs(per_batch[0] - per_batch[1]).max() > 1e-3 * np.abs(per_batch[1]).max()  # other weights, other KL


def test_weights_and_frames_the_model_cannot_read_are_refused() -> None:
    worker = _worker()
    learner = _learner(worker, updates=3)
    labeller = _labeller(worker)
    other = dataclasses.replace(worker.spec, factor_sizes=(6,) * worker.spec.num_factors)  # a 6x6 grid
    with pytest.raises(ValueError, match="another factor layout"):
        LatentActionLabeller(labeller.cfg, other).load_weights(_round_trip(learner))
    cdl = LatentActionLabeller(dataclasses.replace(labeller.cfg, method="cdl"), worker.spec)
    with pytest.raises(ValueError, match="weights of method 'flam'"):
        cdl.load_weights(_round_trip(learner))
    labeller.load_weights(_round_trip(learner))
    small = worker.frames_of(worker.collect())
    small = dataclasses.replace(small, frames=np.ascontiguousarray(small.frames[:, ::2, ::2]), labels=None)
    with pytest.raises(ProtocolError, match="the FLAM model reads 32x32"):
        labeller.label(small)


def test_a_restarted_labeller_keeps_its_counts_and_bounds_its_first_version(tmp_path) -> None:
    worker = _worker()
    learner = _learner(worker, updates=3)
    labeller = _labeller(worker)
    labeller.load_weights(_round_trip(learner))
    labeller.label(worker.frames_of(worker.collect()))
    labeller.checkpoint(tmp_path / "x.pt")
    again = _labeller(worker)
    assert again.restore(tmp_path / "x.pt")
    assert again.labelled_steps == labeller.labelled_steps and again.run_slot_kl() == labeller.run_slot_kl()
    assert again.slot_kl() == []  # the recent window starts afresh
    assert again.versions.known == labeller.weights_version and not again.ready
    assert not _labeller(worker).restore(tmp_path / "missing.pt")
