"""The run summary's weight-broadcast section: versions per worker, lag distribution, drops, plot."""
from __future__ import annotations

from pathlib import Path

from proto.messages import ServiceStats
from services.supervisor.config import RunConfig
from services.supervisor.report import plot_policy, policy_summary
from services.supervisor.supervisor import Supervisor


def test_policy_summary_reads_the_last_beats() -> None:
    stats = {("policy-learner", "0"): {"policy_version": 7.0, "lag_0": 30.0, "lag_1": 12.0, "lag_over": 2.0,
                                       "lag_10": 1.0, "dropped_stale": 2.0, "dropped_random_policy": 5.0},
             ("env-worker", "1"): {"policy_version": 6.0}, ("env-worker", "0"): {"policy_version": 7.0},
             ("dynamics-learner", "0"): {"updates": 100.0}}
    out = policy_summary(stats, [(1.0, "policy-learner", "0", 1.0), (1.5, "env-worker", "0", 1.0)])
    assert out["published_version"] == 7 and out["worker_versions"] == {"0": 7, "1": 6}
    assert list(out["lag_histogram"].items()) == [("0", 30), ("1", 12), ("10", 1), ("over", 2)]  # numeric order
    assert out["dropped"] == {"stale": 2, "random_policy": 5}
    assert out["version_timeline"] == [[1.0, "policy-learner/0", 1], [1.5, "env-worker/0", 1]]
    assert "skill_options" not in out


def test_policy_summary_sums_the_skills_workers_started() -> None:
    stats = {("policy-learner", "0"): {"policy_version": 3.0, "decisions": 40.0, "decisions_discarded": 1.0,
                                       "return_grasp:unm": 2.5, "return_reach": -0.25},
             ("env-worker", "0"): {"options_uniform_reach": 4.0, "options_learned_grasp:unm": 9.0},
             ("env-worker", "1"): {"options_learned_grasp:unm": 2.0, "options_learned_push:mov": 1.0}}
    out = policy_summary(stats, [])
    assert out["skill_options"] == {"learned": {"grasp:unm": 11, "push:mov": 1}, "uniform": {"reach": 4}}
    assert (out["decisions"], out["decisions_discarded"]) == (40, 1)
    assert out["mean_return_by_option"] == {"grasp:unm": 2.5, "reach": -0.25}


def test_plot_policy_writes_a_png(tmp_path: Path) -> None:
    out = policy_summary({("policy-learner", "0"): {"policy_version": 2.0, "lag_0": 3.0}},
                         [(0.5, "policy-learner", "0", 1.0), (0.7, "env-worker", "0", 1.0),
                          (1.5, "policy-learner", "0", 2.0)])
    plot_policy(out, tmp_path / "policy.png")
    assert (tmp_path / "policy.png").read_bytes()[:4] == b"\x89PNG"


def test_supervisor_records_version_changes_only() -> None:
    sup = Supervisor(RunConfig(router_port=7447, collector="ppo", run_dir="/tmp/unused-run"))
    for version in (0, 1, 1, 2):
        beat = ServiceStats("env-worker", "0", {"policy_version": float(version), "env_steps": 1.0})
        sup._track_policy_version(beat)
        sup.progress.on_stats(beat)
    sup._track_policy_version(ServiceStats("dynamics-learner", "0", {"policy_version": 5.0}))
    assert [(svc, v) for _, svc, _, v in sup.policy_timeline] == [("env-worker", 0.0), ("env-worker", 1.0),
                                                                   ("env-worker", 2.0)]
