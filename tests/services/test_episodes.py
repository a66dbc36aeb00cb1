"""Task performance of the collection policy: per-episode return, success and stages, into the summary."""
from __future__ import annotations

import io

from proto.messages import ServiceStats
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.env_worker.episodes import EpisodeStats
from services.runtime.config import build_config
from services.supervisor.progress import Progress


def test_episode_stats_by_hand() -> None:
    stats = EpisodeStats(num_stages=4, window=2)
    assert stats.values() == {}
    for reward, info, done in ((0.0, {}, False), (1.0, {"success": True, "num_stages": 4}, True),
                               (0.0, {"success": False, "num_stages": 1}, True),
                               (0.5, {"success": False, "num_stages": 2}, True)):
        stats.step(reward, info, done)
    assert stats.finished == 3  # the window keeps the last two
    assert stats.values() == {"return_mean": 0.25, "success_rate": 0.0, "stages_mean": (0.25 + 0.5) / 2}


def test_a_household_worker_reports_its_task_performance() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="installing-printer", batch_steps=512))
    worker.collect()
    values = worker.episodes.values()
    assert worker.episodes.finished >= 3 and set(values) == {"return_mean", "success_rate", "stages_mean"}
    assert 0.0 <= values["stages_mean"] <= 1.0 and 0.0 <= values["success_rate"] <= 1.0


def test_chemical_has_returns_but_no_success_or_stages() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=120))
    worker.collect()
    assert set(worker.episodes.values()) == {"return_mean"}


def test_progress_means_over_the_workers_that_report() -> None:
    p = Progress(stream=io.StringIO(), interactive=False)
    p.on_stats(ServiceStats("env-worker", "0", {"success_rate": 0.5}))
    p.on_stats(ServiceStats("env-worker", "1", {"success_rate": 1.0}))
    p.on_stats(ServiceStats("env-worker", "2", {"env_steps": 3.0}))
    assert p.mean("env-worker", "success_rate") == 0.75 and p.mean("env-worker", "stages_mean") is None
