"""The whole pipeline in one process over the in-memory bus: reports arrive, bad input is survived."""
from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from proto import topics
from proto.codec import decode, encode
from proto.messages import GraphReport, ServiceStats, TransitionBatch
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.inprocess import InProcessStack
from tests import waiting


wait_for = functools.partial(waiting.wait_for, interval=0.05)

@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    torch.set_num_threads(1)
    cfg = build_config(RunConfig, graph="chain", num_objects=3, run_dir=str(tmp_path_factory.mktemp("run")),
                       run_id="t", cdl_feature_hidden=16, cdl_feature_dim=16, cdl_predictor_hidden=16,
                       cdl_batch_size=32, evaluator_min_interval_s=0.2, learner_publish_every_s=0.3,
                       worker_max_steps_per_second=3000, progress=False)
    overrides = {"dynamics-learner": {"warmup_steps": 500}, "graph-evaluator": {"min_heldout": 100}}
    s = InProcessStack(cfg, config_overrides=overrides).start()
    watcher = s.transport()
    s.reports, s.learner = [], []
    watcher.subscribe(topics.graph("t"), lambda k, p: s.reports.append(decode(p, GraphReport)))
    watcher.subscribe(topics.stats("t", "dynamics-learner"), lambda k, p: s.learner.append(decode(p, ServiceStats)))
    s.watcher = watcher
    yield s
    s.stop()


def test_graph_reports_arrive_with_scores(stack) -> None:
    report = wait_for(lambda: stack.reports and stack.reports[-1], 60, "a graph report")
    assert report.cmi.shape == (9, 10) and report.true_graph is not None
    assert 0.0 <= report.metrics["f1"] <= 1.0 and report.metrics["accuracy"] > 0.5
    assert set(report.controllable) | set(report.action_relevant) | set(report.action_irrelevant) == set(range(9))


def test_malformed_and_inconsistent_messages_are_counted_and_survived(stack) -> None:
    wait_for(lambda: stack.learner and stack.learner[-1].values.get("updates", 0) > 0, 60, "learner updates")
    key = topics.transitions("t", "evil")
    stack.watcher.publish(key, b"\x93not msgpack at all")
    t = 4
    wrong_width = TransitionBatch(worker_id="evil", seq=0, policy_version=0, state=np.zeros((t, 5), np.float32),
                                  action=np.zeros((t, 1), np.float32), reward=np.zeros(t, np.float32),
                                  next_state=np.zeros((t, 5), np.float32), terminated=np.zeros(t, bool),
                                  truncated=np.zeros(t, bool), episode_id=np.zeros(t, np.int64),
                                  step=np.zeros(t, np.int32))
    stack.watcher.publish(key, encode(wrong_width))
    before = stack.learner[-1].values["updates"]
    wait_for(lambda: stack.learner[-1].values["updates"] > before + 5, 30, "training to go on")
    assert stack.learner[-1].values["messages_rejected"] == 2  # one malformed, one inconsistent
    assert all(t.is_alive() for t in stack.threads)
