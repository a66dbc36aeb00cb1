"""Config dataclasses map one-to-one onto flags and environment variables."""
from __future__ import annotations

import dataclasses
import json

import pytest

from services.dynamics_learner.config import DynamicsLearnerConfig
from services.env_worker.config import EnvWorkerConfig
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.policy_learner.config import PolicyLearnerConfig
from services.runtime.config import build_config, config_from_dict, flags, parse_config, to_environ, write_config
from services.supervisor.config import RunConfig


def test_defaults_env_then_flags() -> None:
    cfg = parse_config(EnvWorkerConfig, [], {})
    assert cfg == EnvWorkerConfig()
    cfg = parse_config(EnvWorkerConfig, ["--graph", "chain", "--local-graphs", "true"],
                       {"CAUSEWAY_GRAPH": "collider", "CAUSEWAY_NUM_OBJECTS": "4"})
    assert cfg.env_options.graph == "chain" and cfg.env_options.num_objects == 4 and cfg.local_graphs is True


def test_environ_round_trip_for_every_service_config() -> None:
    for cls in (EnvWorkerConfig, DynamicsLearnerConfig, RunConfig, GraphEvaluatorConfig, PolicyLearnerConfig,
                IntrinsicRewardConfig):
        original = dataclasses.replace(cls(), run_id="abc") if hasattr(cls(), "run_id") else cls()
        assert parse_config(cls, [], to_environ(original)) == original


def test_bad_values_are_clear_errors(capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        parse_config(EnvWorkerConfig, [], {"CAUSEWAY_NUM_OBJECTS": "ten"})
    assert exit_.value.code == 2 and "CAUSEWAY_NUM_OBJECTS" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_config(EnvWorkerConfig, ["--num-objects", "ten"], {})


@pytest.mark.parametrize("argv,environ,message", [
    (["--env", "nope"], {}, "--env: invalid choice 'nope' (choose from 'chemical'"),
    ([], {"CAUSEWAY_METHOD": "nope"}, "--method: invalid choice 'nope' (choose from 'cdl'"),
    (["--target-metric", "nope"], {}, "invalid choice 'nope' (choose from 'accuracy'"),
    (["--collector", "dqn"], {}, "choose from 'random', 'ppo', 'sac'"),
    (["--intrinsic", "nope"], {}, "choose from 'none', 'preddiff'"),
    (["--task", "nope"], {}, "choose from '', 'clean-car', 'clean-rag', 'diamond'"),
    (["--cdl-lr", "nan"], {}, "lr must be a positive finite number, got nan"),
    (["--cdl-batch-size", "0"], {}, "batch_size must be >= 1"),
    (["--learner-replay-capacity", "0"], {}, "replay_capacity must be >= 1"),
    (["--workers", "-1"], {}, "workers must be >= 1"),
    (["--lr", "0.1"], {}, "unrecognized arguments: --lr"),  # no abbreviations, no old names
])
def test_enumerations_and_ranges_are_refused_before_anything_starts(argv, environ, message, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        parse_config(RunConfig, argv, environ, prog="causeway run")
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err


def test_sections_compose_service_and_method_settings_as_prefixed_flags() -> None:
    cfg = parse_config(RunConfig, ["--cdl-lr", "1e-3", "--learner-replay-capacity", "7", "--policy-hide", "mk",
                                   "--graph", "chain"], {"CAUSEWAY_EVALUATOR_MIN_INTERVAL_S": "9"})
    assert cfg.models.cdl.lr == 1e-3 and cfg.learner.replay_capacity == 7 and cfg.policy.hide == "mk"
    assert cfg.env_options.graph == "chain" and cfg.evaluator.min_interval_s == 9.0
    assert RunConfig().learner.publish_every_s == 5.0 != DynamicsLearnerConfig().publish_every_s  # the run's default
    names = {flag.name for flag in flags(RunConfig)}
    assert {"learner-seed", "learner-run-id", "worker-env", "policy-algo", "intrinsic-reward"}.isdisjoint(names)
    assert build_config(RunConfig, graph="chain", cdl_lr=1e-3, policy_hide="mk") == parse_config(
        RunConfig, ["--graph", "chain", "--cdl-lr", "0.001", "--policy-hide", "mk"], {})
    with pytest.raises(TypeError, match="no setting lr"):
        build_config(RunConfig, lr=1e-3)


def test_write_config_and_read_it_back(tmp_path) -> None:
    cfg = build_config(RunConfig, graph="chain", cdl_lr=1e-3, learner_replay_capacity=9)
    write_config(cfg, tmp_path / "c.json")
    data = json.loads((tmp_path / "c.json").read_text())
    assert data["env_options"]["graph"] == "chain" and data["models"]["cdl"]["lr"] == 1e-3
    assert config_from_dict(RunConfig, data) == cfg
    # a run directory written before settings moved into sections: same-named flags are recognised
    old = config_from_dict(RunConfig, {"graph": "collider", "num_objects": 4, "lr": 0.5, "env": "chemical"})
    assert (old.env_options.graph, old.env_options.num_objects, old.models.cdl.lr) == ("collider", 4, 3e-3)


def test_progress_totals_survive_a_restarted_counter() -> None:
    import io

    from proto.messages import ServiceStats
    from services.supervisor.progress import Progress

    p = Progress(stream=io.StringIO(), interactive=False)
    for steps in (100.0, 300.0, 50.0, 80.0):  # the worker restarts after 300 and counts from zero
        p.on_stats(ServiceStats("env-worker", "0", {"env_steps": steps}))
    p.on_stats(ServiceStats("env-worker", "1", {"env_steps": 20.0}))
    assert p.env_steps() == 300 + 80 + 20
    # a learner resumes its update count from its checkpoint: 1,200 done, killed, resumed at 1,000
    for updates, resumed in ((800.0, 0.0), (1200.0, 0.0), (1000.0, 1000.0), (1100.0, 1000.0)):
        p.on_stats(ServiceStats("dynamics-learner", "0", {"updates": updates, "resumed_at_update": resumed}))
    assert p.updates() == 1100


def test_progress_line_waits_only_for_the_reports_the_run_gives() -> None:
    import io

    import numpy as np

    from proto.messages import LocalGraphReport, ServiceStats
    from services.supervisor.progress import Progress

    assert "graph: waiting for the first report" in Progress(stream=io.StringIO(), interactive=False).line(0)
    elden = Progress(stream=io.StringIO(), interactive=False, global_graph=False, local_graphs=True)
    assert elden.line(0).endswith("| local graphs: waiting for the first report") and "graph:" not in elden.line(0)
    elden.on_local_report(LocalGraphReport(
        kind="elden", estimator="jacobian", weights_version=7, env_steps=10, updates=5, factor_names=("a", "b"),
        threshold=3e-4, scores=np.zeros((0, 2, 3), np.float32), truth=np.zeros((0, 2, 3), np.uint8),
        metrics={"roc_auc": 0.8512, "pr_auc": 0.2, "best_f1": 0.7149}, num_transitions=1000, timestamp=0.0))
    assert elden.line(0).endswith("| local graphs v7 ROC AUC 0.851 best F1 0.715")
    flam = Progress(stream=io.StringIO(), interactive=False, global_graph=False)
    assert flam.line(0).endswith("updates 0 (0.0/s)")  # no evaluator: nothing to wait for; no NLL to show
    flam.on_stats(ServiceStats("dynamics-learner", "0", {"updates": 3.0, "live_psnr": 41.234, "live_dci_d": 0.5,
                                                        "live_slot0_kl": 2.0}))
    assert flam.line(0).endswith("| live psnr 41.2 dci_d 0.5")


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
