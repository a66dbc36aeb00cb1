"""factor-extractor core and the env-worker's frames: frames match the states, the slots are learned and
then frozen, FrameBatches become TransitionBatches of slot factors that fit their spec, checkpoints resume."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from envs.chemical_pixels import ChemicalPixelsEnv
from proto.codec import ProtocolError, decode, encode
from proto.fits import check_fits
from proto.messages import FrameBatch, ServiceStats
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.factor_extractor.config import FactorExtractorConfig
from services.factor_extractor.core import FactorExtractorCore, slot_graph
from services.runtime.config import build_config
from services.supervisor.report_slots import SCORES, slot_facts

torch.set_num_threads(1)


def _worker(**kw) -> EnvWorkerCore:
    return EnvWorkerCore(build_config(EnvWorkerConfig, env="chemical-pixels", num_objects=3, graph="chain",
                                      episode_length=10, batch_steps=24, publish_frames=True, **kw))


def _extractor(tmp_path, **kw) -> FactorExtractorConfig:
    settings = {"ae_updates": 2, "slot_updates": 3, "warmup_frames": 16, "replay_frames": 64, "statistics_frames": 32,
                "identity_frames": 32, "run_dir": str(tmp_path), "slot_batch_size": 8, **kw}
    return build_config(FactorExtractorConfig, **settings)


def test_frames_are_the_rendered_states_each_sent_once() -> None:
    """Two workers of one seed take the same steps: one sends frames, the other states."""
    batch, transitions = _worker().collect_frames(), _worker().collect()
    assert isinstance(batch, FrameBatch) and len(batch) == 24 and batch.seq == 0
    assert len(batch.frames) == 24 + 1 + 2  # T + 1, plus the resets after steps 10 and 20
    render = ChemicalPixelsEnv(graph="chain", num_objects=3)
    rendered, labels = render.render_states(transitions.state)
    assert np.array_equal(batch.frames[batch.state_frame], rendered)
    assert np.array_equal(batch.labels[batch.state_frame], labels)
    assert np.array_equal(batch.frames[batch.next_frame], render.render_states(transitions.next_state)[0])
    assert np.array_equal(batch.action, transitions.action) and np.array_equal(batch.truncated, transitions.truncated)


def test_worker_refuses_frames_from_an_env_that_renders_none() -> None:
    with pytest.raises(ValueError, match="renders no frames"):
        EnvWorkerCore(build_config(EnvWorkerConfig, env="chemical", num_objects=3, publish_frames=True))


def test_stride_downsamples_frames_and_labels() -> None:
    batch = _worker(frame_stride=2).collect_frames()
    assert batch.frames.shape[1:] == (16, 16, 3) and batch.labels.shape[1:] == (16, 16)


def test_slots_are_learned_then_frozen_and_published_as_transitions(tmp_path) -> None:
    worker = _worker()
    core = FactorExtractorCore(_extractor(tmp_path, warmup_frames=30), worker.spec)
    assert core.slot_config.num_slots == 4  # 3 objects + background
    assert core.ingest(worker.collect_frames()) is None and not core.may_update  # 27 frames: warm-up is 30
    assert core.ingest(worker.collect_frames()) is None and core.may_update
    phases = [core.train_step()["phase"] for _ in range(5)]
    assert phases == [0, 0, 1, 1, 1] and core.ready and not core.may_update
    batch = worker.collect_frames()
    out = core.transitions(batch)
    spec = core.spec()
    assert spec.state_dim == 4 * 16 and spec.factor_names == ("background", "obj0", "obj1", "obj2")
    assert spec.action_size == worker.spec.action_size
    assert np.array_equal(spec.global_graph, slot_graph(worker.spec))
    check_fits(spec, out)
    decode(encode(spec))
    assert out.state.shape == (24, 64) and np.isfinite(out.state).all()
    assert (out.episode_id == batch.episode_id).all() and out.seq == batch.seq and out.worker_id == "w0"
    inside = ~(batch.terminated | batch.truncated)[:-1]  # within an episode, s'_t is s_t+1's frame: same slots
    assert np.array_equal(out.next_state[:-1][inside], out.state[1:][inside])
    assert not np.allclose(out.state[0], out.state[1])
    assert np.allclose(out.state, core.ingest(batch).state)  # frozen: ingest publishes


def test_checkpoint_resumes_the_frozen_slots(tmp_path) -> None:
    worker = _worker()
    core = FactorExtractorCore(_extractor(tmp_path), worker.spec)
    for _ in range(2):
        core.ingest(worker.collect_frames())
    while core.may_update:
        core.train_step()
    core.checkpoint(tmp_path / "x.pt")
    resumed = FactorExtractorCore(_extractor(tmp_path), worker.spec)
    assert resumed.restore(tmp_path / "x.pt") and resumed.ready and encode(resumed.spec()) == encode(core.spec())
    batch = worker.collect_frames()
    assert np.array_equal(resumed.transitions(batch).state, core.transitions(batch).state)
    assert resumed.identity_scores == core.identity_scores and resumed.identity_scores
    other = FactorExtractorCore(_extractor(tmp_path, num_slots=6, identity="none"), worker.spec)
    with pytest.raises(ValueError, match="different"):
        other.restore(tmp_path / "x.pt")


def test_frames_that_do_not_fit_are_refused(tmp_path) -> None:
    worker = _worker()
    core = FactorExtractorCore(_extractor(tmp_path), worker.spec)
    batch = worker.collect_frames()
    core.ingest(batch)
    small = dataclasses.replace(batch, frames=batch.frames[:, :16, :16], labels=batch.labels[:, :16, :16])
    with pytest.raises(ProtocolError, match="32-pixel"):
        core.ingest(small)
    with pytest.raises(ProtocolError, match="labels"):
        core.ingest(dataclasses.replace(batch, labels=None))
    with pytest.raises(ProtocolError, match="object 7"):
        core.ingest(dataclasses.replace(batch, labels=np.full_like(batch.labels, 7)))


def test_slot_graph_is_the_object_graph_with_a_background() -> None:
    """Chemical ``full`` on 3 objects: obj0 -> obj2 and obj0, obj1 -> ... as Figure 3.5's object graph;
    the background has its self-edge only and the action reaches every object."""
    spec = ChemicalPixelsEnv(graph="full", num_objects=3).env_spec()
    graph = slot_graph(spec)
    assert graph.shape == (4, 5)
    assert graph[0].tolist() == [1, 0, 0, 0, 0] and graph[:, 0].tolist() == [1, 0, 0, 0]
    assert graph[1:, 1:].tolist() == [[1, 0, 0, 1], [0, 1, 0, 1], [1, 0, 1, 1]]


def test_identity_none_keeps_slot_attentions_order_and_no_truth(tmp_path) -> None:
    worker = _worker()
    core = FactorExtractorCore(_extractor(tmp_path, identity="none"), worker.spec)
    for _ in range(2):
        core.ingest(worker.collect_frames())
    while core.may_update:
        core.train_step()
    spec = core.spec()
    assert spec.factor_names == ("slot0", "slot1", "slot2", "slot3") and spec.global_graph is None
    assert core.identity is None and "identity_slot_accuracy" not in core.progress()


def test_identity_head_waits_for_its_frames_unpublished(tmp_path) -> None:
    """Frozen slots, but fewer frames held than the head is fitted on: frames go on filling the replay and
    nothing is published until it holds them; the first batch after that is published."""
    worker = _worker()
    core = FactorExtractorCore(_extractor(tmp_path, identity_frames=1000), worker.spec)
    assert core.frames_needed() == 64  # at most the replay's size
    for _ in range(2):
        core.ingest(worker.collect_frames())
    while core.may_update:
        core.train_step()
    assert core.learner.frozen and not core.ready and core.replay.size == 54
    assert core.ingest(worker.collect_frames()) is None and core.ready and core.identity_scores["fit_frames"] == 51
    assert core.ingest(worker.collect_frames()) is not None


def test_learned_identity_needs_one_slot_per_segment(tmp_path) -> None:
    with pytest.raises(ValueError, match="num_slots must be 4"):
        FactorExtractorCore(_extractor(tmp_path, num_slots=6), _worker().spec)


def test_published_slots_are_scored_against_the_masks(tmp_path) -> None:
    """Once frozen, every published batch with labels adds to the matching accuracy in the progress."""
    worker = _worker()
    core = FactorExtractorCore(_extractor(tmp_path), worker.spec)
    for _ in range(2):
        core.ingest(worker.collect_frames())
    assert slot_facts(ServiceStats("factor-extractor", "0", core.progress())) == {}  # not frozen yet
    while core.may_update:
        core.train_step()
    progress = core.progress()
    assert 0.0 <= progress["identity_slot_accuracy"] <= 1.0 and "published_identity_slot_accuracy" not in progress
    core.ingest(worker.collect_frames())
    progress = core.progress()
    assert 0.0 <= progress["published_identity_frame_accuracy"] <= progress["published_identity_slot_accuracy"] <= 1.0
    slots = slot_facts(ServiceStats("factor-extractor", "0", progress))["slots"]
    assert set(SCORES) <= set(slots) and -1.0 <= slots["fg_ari"] <= 1.0 and slots["slot_updates"] == 5


def test_slots_frozen_before_they_bind_are_reported(tmp_path) -> None:
    """Three slot updates cannot bind objects: the held-out FG-ARI is low and the core says why."""
    worker = _worker()
    core = FactorExtractorCore(_extractor(tmp_path), worker.spec)
    assert core.binding_warning() is None  # nothing frozen, nothing to report
    for _ in range(2):
        core.ingest(worker.collect_frames())
    while core.may_update:
        core.train_step()
    assert core.ready and core.matching()["fg_ari"] < 0.5
    assert "froze unbound" in core.binding_warning() and "3 slot updates" in core.binding_warning()
    assert slot_facts(ServiceStats("factor-extractor", "0", core.progress()))["slots"]["bound"] is False


@pytest.mark.slow
def test_default_slot_budget_binds_the_objects(tmp_path) -> None:
    """With the extractor's default budget the slots of chemical-pixels bind one object each and the identity
    head names them (1,500 slot updates, the earlier default, left seeds 0 and 2 of 0-5 unbound in benchmarks.slot_binding)."""
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="chemical-pixels", num_objects=4, graph="full",
                                        batch_steps=512, publish_frames=True, seed=1))
    cfg = build_config(FactorExtractorConfig, run_dir=str(tmp_path), seed=1)
    core = FactorExtractorCore(cfg, worker.spec)
    while core.replay is None or core.replay.size < core.frames_needed():
        core.ingest(worker.collect_frames())
    while core.may_update:
        core.train_step()
    scores = core.matching()
    assert core.ready and core.binding_warning() is None
    assert slot_facts(ServiceStats("factor-extractor", "0", core.progress()))["slots"]["bound"] is True
    assert scores["fg_ari"] >= 0.9 and scores["identity_slot_accuracy"] >= 0.9
