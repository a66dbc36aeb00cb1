"""``--method skild`` through the unchanged stack: the learner trains the induced-graph model under
SkiLD's name and the evaluator scores its point-wise CMI local graphs against the true ones."""
from __future__ import annotations

import time

import pytest

from proto import topics
from proto.codec import decode
from proto.messages import GraphReport, LocalGraphReport, Weights
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.inprocess import InProcessStack


def test_a_skild_run_on_installing_printer_publishes_scored_local_graphs(tmp_path) -> None:
    cfg = build_config(RunConfig, method="skild", env="installing-printer", run_dir=str(tmp_path), run_id="sk",
                       learner_publish_every_s=0.5, evaluator_min_interval_s=0.5, evaluator_local_samples=64,
                       worker_max_steps_per_second=2000, progress=False, skild_eligible_after=10)
    assert cfg.models.skild.eligible_after == 10
    stack = InProcessStack(cfg, config_overrides={"dynamics-learner": {"warmup_steps": 100},
                                                  "graph-evaluator": {"min_heldout": 30}})
    found: dict[str, list] = {"local": [], "weights": [], "graph": []}
    for key, topic, kind in (("local", topics.local("sk", "skild"), LocalGraphReport),
                             ("weights", topics.weights("sk", "skild"), Weights),
                             ("graph", topics.graph("sk"), GraphReport)):
        stack.transport().subscribe(topic, lambda _, payload, key=key, kind=kind: found[key].append(decode(payload, kind)))
    stack.start()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(found["local"]) < 2:
            time.sleep(0.2)
    finally:
        stack.stop()
    assert found["weights"] and all(w.model == "skild" for w in found["weights"])
    assert len(found["local"]) >= 2, "no local-graph report from the SkiLD run"
    last = found["local"][-1]
    assert last.kind == "skild" and last.estimator == "pcmi" and last.threshold == pytest.approx(0.02)
    assert last.scores.shape[1:] == (12, 13) and {"roc_auc", "best_f1"} <= set(last.metrics)
    assert not found["graph"]  # chapter 6 defines local graphs only
