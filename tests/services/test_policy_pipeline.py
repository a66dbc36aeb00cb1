"""The policy loop in one process: --collector ppo --intrinsic preddiff on Chemical (3 objects).

env-workers act with the policy-learner's newest weights, the intrinsic-reward service scores their
batches with the dynamics-learner's CDL weights and the evaluator's graph, the policy-learner trains
on the scored batches and publishes new versions.
"""
from __future__ import annotations

import time

import pytest
import torch

from proto import topics
from proto.codec import decode
from proto.messages import ScoredBatch, ServiceStats, TransitionBatch, Weights
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.inprocess import InProcessStack

RUN_SECONDS = 180.0
"""The longest the stack runs: it stops as soon as everything the tests check has been seen (about
20 s on an idle 2-core machine), so a loaded machine makes it slower, not red."""


def _enough(seen: dict[str, list]) -> bool:
    """Every test's condition met (the tests assert them again, precisely)."""
    workers: dict[str, int] = {}
    for batch in list(seen["transitions"]):
        workers[batch.worker_id] = max(workers.get(batch.worker_id, 0), batch.policy_version)
    scored, weights, learner = list(seen["scored"]), list(seen["weights"]), list(seen["learner"])
    return (len(scored) > 20 and any(s.weights_version > 0 and abs(float(s.intrinsic_reward.mean())) > 0
                                     for s in scored)
            and bool(weights) and max(weights) >= 5 and len(workers) == 2 and min(workers.values()) >= 3
            and bool(learner) and learner[-1].values.get("updates", 0) >= 4)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    torch.set_num_threads(1)
    cfg = build_config(RunConfig, graph="chain", num_objects=3, run_dir=str(tmp_path_factory.mktemp("run")),
                       run_id="p", cdl_feature_hidden=16, cdl_feature_dim=16, cdl_predictor_hidden=16,
                       cdl_batch_size=32, evaluator_min_interval_s=0.5, learner_publish_every_s=0.5,
                       worker_max_steps_per_second=2000, progress=False, workers=2, collector="ppo",
                       intrinsic="preddiff")
    overrides = {"dynamics-learner": {"warmup_steps": 500}, "graph-evaluator": {"min_heldout": 100},
                 "policy-learner": {"rollout_batches": 2, "minibatch_size": 128, "epochs": 2, "hidden": 32}}
    stack = InProcessStack(cfg, config_overrides=overrides)
    assert {t.name for t in stack.threads} >= {"policy-learner", "intrinsic-reward", "env-worker-0", "env-worker-1"}
    seen: dict[str, list] = {"scored": [], "transitions": [], "policy": [], "learner": [], "weights": []}
    watcher = stack.transport()
    watcher.subscribe(topics.scored("p"), lambda k, p: seen["scored"].append(decode(p, ScoredBatch)))
    watcher.subscribe(topics.transitions("p"), lambda k, p: seen["transitions"].append(decode(p, TransitionBatch)))
    watcher.subscribe(topics.weights("p", "policy"), lambda k, p: seen["weights"].append(decode(p, Weights).version))
    watcher.subscribe(topics.stats("p", "policy-learner"), lambda k, p: seen["learner"].append(decode(p, ServiceStats)))
    stack.start()
    deadline = time.monotonic() + RUN_SECONDS
    while time.monotonic() < deadline and not _enough(seen):
        time.sleep(0.5)
    time.sleep(1.0)  # the newest learner beat after the last version it published
    alive = all(t.is_alive() for t in stack.threads)
    stack.stop()
    return seen, alive


def test_every_service_stays_up(run) -> None:
    assert run[1]


def test_scored_batches_arrive_with_dynamics_weights(run) -> None:
    scored = run[0]["scored"]
    assert len(scored) > 20
    late = [s for s in scored if s.weights_version > 0]
    assert late and all(s.reward_kind == "preddiff" for s in scored)
    assert any(abs(float(s.intrinsic_reward.mean())) > 0 for s in late)


def test_policy_versions_advance_and_workers_act_with_them(run) -> None:
    seen = run[0]
    assert seen["weights"] and max(seen["weights"]) >= 5 and seen["weights"] == sorted(seen["weights"])
    versions = {b.worker_id: [] for b in seen["transitions"]}
    for b in seen["transitions"]:
        versions[b.worker_id].append(b.policy_version)
    assert set(versions) == {"w0", "w1"}
    for vs in versions.values():
        assert vs == sorted(vs) and max(vs) >= 3  # every worker follows the newest policy
    last = seen["learner"][-1].values
    assert last["updates"] >= 4 and last["policy_version"] == last["updates"] + 1
