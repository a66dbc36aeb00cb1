"""Transitions lost on the way to the learner (issue 20 item 4): seq gaps per worker life, reordering,
duplicates, restarts of the worker and of the learner."""
from __future__ import annotations

import random

import torch

from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.dynamics_learner.gaps import MISSING_KEPT, SeqGaps
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.runtime.config import build_config


def counts(gaps: SeqGaps) -> tuple[int, int]:
    return gaps.lost_batches, gaps.lost_steps


def test_in_order_batches_lose_nothing() -> None:
    gaps = SeqGaps()
    assert [gaps.observe("w0", 0, s, 256) for s in range(5)] == ["next"] * 5
    assert counts(gaps) == (0, 0)


def test_a_gap_counts_the_batches_between_at_the_length_of_the_batch_after_it() -> None:
    gaps = SeqGaps()
    gaps.observe("w0", 0, 0, 100)
    assert gaps.observe("w0", 0, 4, 100) == "after_gap"
    assert counts(gaps) == (3, 300)
    gaps.observe("w0", 0, 5, 100)
    assert counts(gaps) == (3, 300)


def test_a_life_starts_at_seq_zero_so_its_first_batches_lost_count() -> None:
    gaps = SeqGaps()
    gaps.observe("w0", 0, 2, 64)
    assert counts(gaps) == (2, 128)


def test_workers_are_counted_apart() -> None:
    gaps = SeqGaps()
    for s in range(3):
        gaps.observe("w0", 0, s, 10)
    gaps.observe("w1", 0, 0, 10)
    gaps.observe("w1", 0, 2, 10)
    assert counts(gaps) == (1, 10)


def test_a_restarted_worker_is_no_gap_and_hides_none() -> None:
    gaps = SeqGaps()
    for s in range(10):
        gaps.observe("w0", 0, s, 10)
    assert gaps.observe("w0", 1, 0, 10) == "next"  # seq back to 0 in a new life: no gap, no duplicate
    assert counts(gaps) == (0, 0) and gaps.duplicates == 0
    gaps.observe("w0", 1, 3, 10)  # a gap in the new life still counts
    assert counts(gaps) == (2, 20)
    assert gaps.observe("w0", 0, 10, 10) == "next"  # the old life's last batch, delivered after the new one's
    assert counts(gaps) == (2, 20)


def test_a_late_batch_is_taken_off_the_count_once_and_a_duplicate_counts_nothing() -> None:
    gaps = SeqGaps()
    for s in (0, 1, 3, 4):
        gaps.observe("w0", 0, s, 50)
    assert counts(gaps) == (1, 50)
    assert gaps.observe("w0", 0, 2, 50) == "late"
    assert counts(gaps) == (0, 0)
    assert gaps.observe("w0", 0, 2, 50) == "duplicate"
    assert gaps.observe("w0", 0, 4, 50) == "duplicate"
    assert counts(gaps) == (0, 0) and (gaps.late, gaps.duplicates) == (1, 2)


def test_shuffled_delivery_with_drops_and_repeats_counts_exactly_the_dropped() -> None:
    rng = random.Random(7)
    sent = [(w, life, s) for w in ("w0", "w1") for life in (0, 1) for s in range(200)]
    dropped = set(rng.sample(sent, 40))
    delivered = [b for b in sent if b not in dropped] + rng.sample([b for b in sent if b not in dropped], 25)
    rng.shuffle(delivered)
    gaps = SeqGaps()
    for w, life, s in delivered:
        gaps.observe(w, life, s, 8)
    tails = {(w, life): max(s for w2, l2, s in sent if (w2, l2) == (w, life) and (w2, l2, s) not in dropped)
             for w, life, _ in sent}
    countable = [b for b in dropped if b[2] < tails[b[:2]]]  # a drop after a life's last arrival shows no gap
    assert counts(gaps) == (len(countable), 8 * len(countable))
    assert gaps.duplicates == 25


def test_the_missing_set_is_bounded_and_a_huge_seq_costs_no_loop() -> None:
    gaps = SeqGaps()
    gaps.observe("w0", 0, 2**40, 1)
    assert counts(gaps) == (2**40, 2**40)
    assert len(gaps.lives[("w0", 0)].missing) == MISSING_KEPT
    assert gaps.observe("w0", 0, 5, 1) == "duplicate"  # older than the remembered: stays lost
    assert gaps.observe("w0", 0, 2**40 - 1, 1) == "late"


def test_state_round_trips_through_a_weights_only_checkpoint(tmp_path) -> None:
    gaps = SeqGaps()
    for s in (0, 2, 5):
        gaps.observe("w0", 0, s, 16)
    gaps.observe("w1", 3, 1, 16)
    torch.save(gaps.state_dict(), tmp_path / "g.pt")
    again = SeqGaps()
    again.load_state_dict(torch.load(tmp_path / "g.pt", weights_only=True))
    assert again.stats() == gaps.stats()
    assert again.observe("w0", 0, 3, 16) == "late" and again.observe("w0", 0, 6, 16) == "next"


def learner(worker: EnvWorkerCore) -> DynamicsLearnerCore:
    cfg = build_config(DynamicsLearnerConfig, cdl_feature_hidden=8, cdl_feature_dim=8, cdl_predictor_hidden=8,
                       cdl_batch_size=16, warmup_steps=100)
    return DynamicsLearnerCore(cfg, worker.spec)


def test_the_learner_counts_real_batches_across_a_worker_restart_and_its_own(tmp_path) -> None:
    worker_cfg = build_config(EnvWorkerConfig, graph="chain", num_objects=3, batch_steps=64, seed=1)
    worker = EnvWorkerCore(worker_cfg)
    core = learner(worker)
    batches = [worker.collect() for _ in range(4)]
    for b in (batches[0], batches[2], batches[3], batches[3]):
        core.ingest(b)
    assert core.progress()["lost_batches"] == 1 and core.progress()["lost_steps"] == 64
    assert core.progress()["duplicate_batches"] == 1 and core.env_steps == 3 * 64  # the duplicate is not kept
    core.checkpoint(tmp_path / "learner.pt")
    core.ingest(worker.collect())  # taken after the checkpoint: a restarted learner lost it
    resumed = learner(worker)
    assert resumed.restore(tmp_path / "learner.pt") and resumed.progress()["lost_batches"] == 1
    resumed.ingest(worker.collect())
    assert resumed.progress()["lost_batches"] == 2
    restarted = EnvWorkerCore(worker_cfg, generation=1)  # seq from 0 again, a new life
    resumed.ingest(restarted.collect())
    assert resumed.progress()["lost_batches"] == 2 and resumed.env_steps == 4 * 64 + 64


def test_the_summary_takes_the_learners_newest_count() -> None:
    import io

    from proto.messages import ServiceStats
    from services.supervisor.progress import Progress

    p = Progress(stream=io.StringIO(), interactive=False)
    assert p.transitions_lost() == {"batches": 0, "steps": 0}
    p.on_stats(ServiceStats("dynamics-learner", "0", {"lost_batches": 3.0, "lost_steps": 768.0}))
    p.on_stats(ServiceStats("dynamics-learner", "0", {"lost_batches": 2.0, "lost_steps": 512.0, "resumed_at_update": 5}))
    assert p.transitions_lost() == {"batches": 2, "steps": 512}
