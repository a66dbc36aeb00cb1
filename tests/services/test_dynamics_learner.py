"""dynamics-learner: the updates-per-env-step gate, its checkpointed invariant, its plumbing from
``causeway run``, and the supervisor's catch-up after the env-step budget."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from proto.codec import decode
from proto.messages import Control, ServiceStats
from services.runtime.config import build_config
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.runtime.config import parse_config
from services.supervisor.config import RunConfig
from services.supervisor.stop_rules import learner_caught_up
from services.supervisor.supervisor import Supervisor
from services.supervisor.wiring import service_configs

SMALL = dict(cdl_feature_hidden=8, cdl_feature_dim=8, cdl_predictor_hidden=8, cdl_batch_size=16, warmup_steps=100)


def learner_and_worker(ratio: float) -> tuple[DynamicsLearnerCore, EnvWorkerCore]:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3, batch_steps=256))
    return DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **SMALL, updates_per_env_step=ratio), worker.spec), worker


def train_while_allowed(core: DynamicsLearnerCore, limit: int = 1_000) -> int:
    done = 0
    while core.may_update and done < limit:
        core.train_step()
        done += 1
    return done


def test_ratio_gates_updates_to_env_steps_ingested() -> None:
    core, worker = learner_and_worker(0.02)
    assert not core.may_update  # warm-up first
    core.ingest(worker.collect())
    assert train_while_allowed(core) == math.ceil(0.02 * 256) and not core.may_update
    core.ingest(worker.collect())
    train_while_allowed(core)
    assert core.trainer.updates == math.ceil(0.02 * 512) and core.env_steps == 512


def test_no_ratio_trains_as_fast_as_possible() -> None:
    core, worker = learner_and_worker(0.0)
    core.ingest(worker.collect())
    assert train_while_allowed(core, limit=50) == 50 and core.may_update


def test_resume_keeps_the_ratio(tmp_path) -> None:
    core, worker = learner_and_worker(0.02)
    core.ingest(worker.collect())
    train_while_allowed(core)
    core.checkpoint(tmp_path / "learner.pt")
    resumed, _ = learner_and_worker(0.02)
    assert resumed.restore(tmp_path / "learner.pt")
    assert (resumed.trainer.updates, resumed.env_steps) == (core.trainer.updates, 256) and not resumed.may_update
    assert resumed.progress()["resumed_env_steps"] == 256 and core.progress()["resumed_env_steps"] == 0


def test_a_resumed_learner_publishes_versions_above_any_it_published(tmp_path) -> None:
    """Killed after publishing versions its checkpoint does not know, a learner resumes above them."""
    ckpt = tmp_path / "dynamics-learner-0.pt"
    core, worker = learner_and_worker(0.0)
    core.ingest(worker.collect())
    train_while_allowed(core, limit=3)
    core.weights()
    core.checkpoint(ckpt)  # at version 1
    for _ in range(4):  # published after the checkpoint: 2..5
        core.weights()
        core.record_version(ckpt)
    resumed, _ = learner_and_worker(0.0)
    assert resumed.restore(ckpt) and resumed.weights().version == 6
    fresh, _ = learner_and_worker(0.0)  # the checkpoint lost: still above what was published
    ckpt.unlink()
    assert not fresh.restore(ckpt) and fresh.weights().version == 6


def test_run_flag_reaches_the_learner() -> None:
    cfg = parse_config(RunConfig, ["--learner-updates-per-env-step", "0.01", "--catch-up-timeout-s", "30"], {})
    assert (cfg.learner.updates_per_env_step, cfg.catch_up_timeout_s) == (0.01, 30.0)
    assert service_configs(cfg, "tcp/x:1")["dynamics-learner"].updates_per_env_step == 0.01
    assert service_configs(RunConfig(), "tcp/x:1")["dynamics-learner"].updates_per_env_step == 0.0


def test_learning_rate_schedule_flags_reach_the_model() -> None:
    cfg = parse_config(RunConfig, ["--cdl-lr-decay-updates", "30000", "--cdl-lr-final", "2e-4"], {})
    cdl = service_configs(cfg, "tcp/x:1")["dynamics-learner"].models.cdl
    assert (cdl.lr_decay_updates, cdl.lr_final) == (30000, 2e-4)
    assert cdl.lr_at(30000) == pytest.approx(2e-4) and cdl.lr_at(0) == pytest.approx(cfg.models.cdl.lr)


def test_replay_capacity_flag_reaches_the_learner() -> None:
    cfg = parse_config(RunConfig, ["--learner-replay-capacity", "1000000"], {})
    learner = service_configs(cfg, "tcp/x:1")["dynamics-learner"]
    assert learner.replay_capacity == 1_000_000
    assert service_configs(RunConfig(), "tcp/x:1")["dynamics-learner"].replay_capacity == 200_000


class _RecordingBus:
    def __init__(self) -> None:
        self.published: list[tuple[str, bytes]] = []

    def publish(self, key: str, payload: bytes, reliable: bool = True) -> None:
        self.published.append((key, payload))


def supervisor(tmp_path, ratio: float) -> Supervisor:
    sup = Supervisor(build_config(RunConfig, router_port=7447, run_dir=str(tmp_path), max_env_steps=10_000,
                                  learner_updates_per_env_step=ratio, catch_up_timeout_s=60, max_seconds=0,
                                  progress=False))
    sup.bus = _RecordingBus()
    sup.progress.on_stats(ServiceStats("env-worker", "0", {"env_steps": 10_240.0}))
    return sup


def test_budget_pauses_workers_until_the_graph_reflects_the_learner(tmp_path) -> None:
    sup = supervisor(tmp_path, 0.01)
    sup.last_report = SimpleNamespace(updates=60, metrics={})
    sup._check_budget(100.0)
    assert not sup._stop.is_set()
    (key, payload), = sup.bus.published
    assert key.endswith("/control/env-worker") and decode(payload, Control).command == "pause"
    sup._check_budget(100.5)
    assert len(sup.bus.published) == 1  # repeated once a second, not every tick
    sup.last_report = SimpleNamespace(updates=98, metrics={})
    sup._check_budget(101.5)
    assert sup._stop.is_set() and "caught up (98 updates)" in sup.stop_reason and len(sup.bus.published) == 2


def test_catch_up_gives_up_after_its_timeout(tmp_path) -> None:
    sup = supervisor(tmp_path, 0.01)
    sup._check_budget(100.0)
    sup._check_budget(159.0)
    assert not sup._stop.is_set()
    sup._check_budget(160.0)
    assert "did not catch up in 60s" in sup.stop_reason


def test_without_ratio_the_budget_stops_at_once(tmp_path) -> None:
    sup = supervisor(tmp_path, 0.0)
    sup._check_budget(1.0)
    assert sup.stop_reason == "env step budget 10000 reached" and not sup.bus.published


@pytest.mark.parametrize("updates,expected", [(97, False), (98, True), (200, True)])
def test_learner_caught_up_tolerance(updates: int, expected: bool) -> None:
    assert learner_caught_up(SimpleNamespace(updates=updates), 0.01, 10_000) is expected
    assert not learner_caught_up(None, 0.01, 10_000)
