"""env-worker core: batches fit the EnvSpec, episodes and seeds behave, replicas get distinct ids."""
from __future__ import annotations

import dataclasses

import numpy as np

from proto.codec import decode, encode
from proto.fits import check_fits
from services.runtime.config import build_config
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore, resolve_worker_index


def test_batches_fit_the_spec_and_round_trip() -> None:
    core = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=120, local_graphs=True))
    batch = core.collect()
    check_fits(core.spec, batch)
    assert len(batch) == 120 and batch.seq == 0 and core.collect().seq == 1
    assert batch.truncated.sum() == 2 and batch.episode_id[-1] == 2  # 50-step episodes
    assert (batch.step[:50] == np.arange(50)).all()
    assert np.array_equal(batch.state[1:50], batch.next_state[:49])
    assert batch.local_graph.shape == (120, 9, 10)
    again = decode(encode(batch))
    assert np.array_equal(again.state, batch.state)


def test_worker_seeds_are_seed_plus_index() -> None:
    a = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=64, seed=1, worker_index=1)).collect()
    b = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=64, seed=2, worker_index=0)).collect()
    c = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=64, seed=1, worker_index=0)).collect()
    assert np.array_equal(a.next_state, b.next_state) and np.array_equal(a.action, b.action)
    assert not np.array_equal(a.action, c.action)


def test_replicas_derive_distinct_indices_from_hostname(monkeypatch) -> None:
    import socket
    cfg = build_config(EnvWorkerConfig, worker_index=-1)
    monkeypatch.setattr(socket, "gethostname", lambda: "causeway-env-worker-1")
    one = resolve_worker_index(cfg)
    monkeypatch.setattr(socket, "gethostname", lambda: "causeway-env-worker-2")
    two = resolve_worker_index(cfg)
    assert one.worker_index != two.worker_index and one.instance == "causeway-env-worker-1"
    assert resolve_worker_index(dataclasses.replace(cfg, worker_index=3)).worker_index == 3


def test_a_restarted_worker_draws_new_seeds_and_episode_ids(tmp_path) -> None:
    from services.env_worker.core import GENERATION_EPISODES, next_generation

    path = tmp_path / "checkpoints" / "env-worker-0.json"
    assert [next_generation(path) for _ in range(3)] == [0, 1, 2]
    cfg = build_config(EnvWorkerConfig, num_objects=3, batch_steps=64)
    first, again, restarted = (EnvWorkerCore(cfg, g).collect() for g in (0, 0, 1))
    assert np.array_equal(first.state, again.state)
    assert not np.array_equal(first.state, restarted.state)
    assert restarted.episode_id.min() >= GENERATION_EPISODES


def test_a_restarted_worker_counts_its_episodes_from_zero() -> None:
    """The beat's ``episodes`` is a count (the run's total adds a restarted worker's to its
    predecessor's), not the generation-offset episode id: a resumed run once reported 1,000,033,372."""
    from services.env_worker.core import GENERATION_EPISODES

    cfg = build_config(EnvWorkerConfig, num_objects=3, batch_steps=64, episode_length=8)
    for generation in (0, 1):
        core = EnvWorkerCore(cfg, generation)
        batch = core.collect()
        assert core.episode >= GENERATION_EPISODES * generation
        assert core.episodes_finished == int(np.sum(batch.terminated | batch.truncated)) == 8
