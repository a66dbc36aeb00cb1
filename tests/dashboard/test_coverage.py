"""SkiLD's induced-graph coverage on the live page and in the summary, from a policy-learner beat."""
from __future__ import annotations

import pytest

from proto.messages import ServiceStats
from services.dashboard.core import DashboardState
from services.dashboard.coverage import induced_coverage
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.report_skills import skill_facts
from services.supervisor.wiring import resolve, service_configs

BEAT = {"coverage_episodes_pretrain": 40.0, "coverage_pretrain: table, printer -> printer": 0.25,
        "coverage_pretrain: agent, printer -> printer": 0.5, "coverage_episodes_task": 0.0,
        "phase_task": 1.0, "pretrain_steps": 2048.0, "task_steps": 512.0, "targets": 9.0, "updates": 5.0}


def test_beat_to_coverage_blocks() -> None:
    got = induced_coverage(BEAT)
    assert got == {"pretrain": {"episodes": 40, "rows": {"agent, printer -> printer": 0.5,
                                                         "table, printer -> printer": 0.25}},
                   "task": {"episodes": 0, "rows": {}}}
    assert list(got["pretrain"]["rows"]) == ["agent, printer -> printer", "table, printer -> printer"]
    assert induced_coverage({"updates": 3.0}) is None


def test_snapshot_carries_the_coverage_of_the_policy_learner() -> None:
    state = DashboardState()
    state.add_stats("r", ServiceStats("policy-learner", "0", BEAT, 1.0), now=1.0)
    state.add_stats("r", ServiceStats("env-worker", "0", {"env_steps": 5.0}, 1.0), now=1.0)
    assert state.snapshot("r", now=2.0)["induced_coverage"]["pretrain"]["episodes"] == 40
    plain = DashboardState()
    plain.add_stats("p", ServiceStats("policy-learner", "0", {"updates": 1.0}, 1.0), now=1.0)
    assert plain.snapshot("p", now=2.0)["induced_coverage"] is None


def test_summary_block() -> None:
    facts = skill_facts(ServiceStats("policy-learner", "0", BEAT, 1.0))
    assert facts["skild"]["phase"] == "task" and facts["skild"]["pretrain_steps"] == 2048
    assert facts["induced_coverage"]["pretrain"]["rows"]["table, printer -> printer"] == 0.25
    assert skill_facts(None) == {} and skill_facts(ServiceStats("policy-learner", "0", {}, 1.0)) == {}


def test_wiring_of_a_skild_run(tmp_path) -> None:
    cfg = resolve(build_config(RunConfig, method="skild", env="installing-printer", run_dir=str(tmp_path),
                               policy_skild_graphs="true", router_port=1))
    configs = service_configs(cfg, "tcp/127.0.0.1:1")
    assert configs["policy-learner"].skild and configs["env-worker"].skild and configs["env-worker"].local_graphs
    assert not configs["env-worker"].follow_policy and not configs["graph-evaluator"].induced_graphs
    pcmi = resolve(build_config(RunConfig, method="skild", env="installing-printer", run_dir=str(tmp_path),
                                router_port=1))
    assert service_configs(pcmi, "tcp/127.0.0.1:1")["graph-evaluator"].induced_graphs


@pytest.mark.parametrize("flags, message", [
    ({"collector": "ppo"}, "--collector random"),
    ({"max_env_steps": 1000, "policy_skild_pretrain_steps": 1000}, "no task learning"),
    ({"env": "chemical"}, "categorical"),
])
def test_bad_skild_runs_are_refused_before_anything_starts(tmp_path, flags, message) -> None:
    settings = {"method": "skild", "env": "installing-printer", "run_dir": str(tmp_path), "router_port": 1, **flags}
    with pytest.raises(ValueError, match=message):
        resolve(build_config(RunConfig, **settings))
