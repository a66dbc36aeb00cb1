"""Run configuration of the policy services: --collector, --intrinsic and --task select what starts."""
from __future__ import annotations

import pytest

from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.wiring import MODULES, learning_services, resolve, service_configs


def test_default_run_is_unchanged() -> None:
    cfg = resolve(RunConfig(router_port=7447))
    assert cfg.env == "chemical" and learning_services(cfg) == ("dynamics-learner", "graph-evaluator")
    assert not service_configs(cfg, "tcp/x:1")["env-worker"].follow_policy


def test_policy_run_starts_the_policy_services_and_workers_follow() -> None:
    cfg = resolve(build_config(RunConfig, router_port=7447, collector="ppo", intrinsic="preddiff", task="match",
                               policy_abstraction=False, policy_max_policy_lag=2, metrics_base_port=9100))
    assert cfg.env == "chemical-match"
    assert learning_services(cfg) == ("dynamics-learner", "graph-evaluator", "policy-learner", "intrinsic-reward")
    configs = service_configs(cfg, "tcp/x:1")
    policy, scorer, worker = configs["policy-learner"], configs["intrinsic-reward"], configs["env-worker"]
    assert (policy.algo, policy.scored, policy.abstraction, policy.max_policy_lag) == ("ppo", True, False, 2)
    assert (scorer.reward, policy.metrics_port, scorer.metrics_port) == ("preddiff", 9104, 9105)
    assert worker.follow_policy and worker.env == "chemical-match"
    assert set(learning_services(cfg)) <= set(MODULES)
    plain = resolve(RunConfig(router_port=7447, collector="ppo"))
    assert learning_services(plain)[-1] == "policy-learner" and not service_configs(plain, "x")["policy-learner"].scored
    assert not service_configs(plain, "x")["policy-learner"].skills


def test_ppo_on_manipulation_acts_over_skills_and_sac_over_motor_actions() -> None:
    ppo = resolve(build_config(RunConfig, router_port=7447, env="manipulation", collector="ppo",
                               intrinsic="preddiff", policy_hide="mk"))
    assert service_configs(ppo, "x")["policy-learner"].skills  # the chapter's PPO over skills with PredDiff
    assert service_configs(ppo, "x")["policy-learner"].hide == "mk"
    sac = resolve(RunConfig(router_port=7447, env="manipulation", collector="sac"))
    assert not service_configs(sac, "x")["policy-learner"].skills


@pytest.mark.parametrize("bad", [dict(collector="dqn"), dict(intrinsic="elden", collector="ppo"), dict(task="push"),
                                 dict(intrinsic="preddiff"), dict(collector="sac", task="match")])
def test_invalid_selections_are_refused(bad: dict) -> None:
    with pytest.raises(ValueError):
        resolve(build_config(RunConfig, router_port=7447, **bad))
