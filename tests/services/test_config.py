"""Config dataclasses map one-to-one onto flags and environment variables."""
from __future__ import annotations

import dataclasses
import json

import pytest

from services.dynamics_learner.config import DynamicsLearnerConfig
from services.env_worker.config import EnvWorkerConfig
from services.runtime.config import parse_config, to_environ, write_config
from services.supervisor.config import RunConfig


def test_defaults_env_then_flags() -> None:
    cfg = parse_config(EnvWorkerConfig, [], {})
    assert cfg == EnvWorkerConfig()
    cfg = parse_config(EnvWorkerConfig, ["--graph", "chain", "--local-graphs", "true"],
                       {"CAUSEWAY_GRAPH": "collider", "CAUSEWAY_NUM_OBJECTS": "4"})
    assert cfg.graph == "chain" and cfg.num_objects == 4 and cfg.local_graphs is True


def test_environ_round_trip_for_every_service_config() -> None:
    for cls in (EnvWorkerConfig, DynamicsLearnerConfig, RunConfig):
        original = dataclasses.replace(cls(), run_id="abc") if hasattr(cls(), "run_id") else cls()
        assert parse_config(cls, [], to_environ(original)) == original


def test_bad_values_are_clear_errors() -> None:
    with pytest.raises(SystemExit, match="CAUSEWAY_NUM_OBJECTS"):
        parse_config(EnvWorkerConfig, [], {"CAUSEWAY_NUM_OBJECTS": "ten"})
    with pytest.raises(SystemExit):
        parse_config(EnvWorkerConfig, ["--num-objects", "ten"], {})


def test_write_config(tmp_path) -> None:
    write_config(RunConfig(graph="chain"), tmp_path / "c.json")
    assert json.loads((tmp_path / "c.json").read_text())["graph"] == "chain"


def test_progress_totals_survive_a_restarted_counter() -> None:
    import io

    from proto.messages import ServiceStats
    from services.supervisor.progress import Progress

    p = Progress(stream=io.StringIO(), interactive=False)
    for steps in (100.0, 300.0, 50.0, 80.0):  # the worker restarts after 300 and counts from zero
        p.on_stats(ServiceStats("env-worker", "0", {"env_steps": steps}))
    p.on_stats(ServiceStats("env-worker", "1", {"env_steps": 20.0}))
    assert p.env_steps() == 300 + 80 + 20


def test_object_level_graph_collapses_factors() -> None:
    import numpy as np

    from services.supervisor.report import object_level

    names = ("a.x", "a.y", "b.x")
    adjacency = np.array([[1, 0, 0, 1], [0, 1, 1, 0], [0, 0, 1, 0]], dtype=np.uint8)
    graph, objects = object_level(adjacency, names)
    assert objects == ["a", "b"]
    assert graph.tolist() == [[1, 1, 1], [0, 1, 0]]


def test_object_scores_count_cross_object_edges_only() -> None:
    import numpy as np

    from services.supervisor.report import object_scores

    names = ("a.x", "a.y", "b.x", "c.x")
    truth = np.zeros((4, 5), dtype=np.uint8)
    truth[0, 2] = truth[2, 4] = truth[3, 3] = 1      # b -> a, action -> b, c -> c (not scored)
    learned = np.zeros_like(truth)
    learned[0, 1] = learned[0, 2] = learned[3, 0] = 1  # a -> a (not scored), b -> a, a -> c (spurious)
    scores = object_scores(learned, truth, names)
    assert scores["true_edges"] == 2 and scores["missed"] == ["action -> b"] and scores["spurious"] == ["a -> c"]
    assert scores["precision"] == 0.5 and scores["recall"] == 0.5 and scores["f1"] == 0.5
    assert object_scores(learned, None, names) is None
    assert object_scores(learned[:3, :4], truth[:3, :4], ("a", "b", "c")) is None  # Chemical: no objects
