"""``causeway run --task match --collector ppo`` end to end: the summary gains the weight broadcast
(versions per worker, lag distribution) and the post-run evaluation of the run's own models
(k-step prediction ID/OOD, Match returns of CEM + CDL, of the policy and of random actions)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]


def test_match_run_reports_policy_broadcast_and_ood_evaluation(tmp_path: Path) -> None:
    run_dir = tmp_path / "match"
    cmd = [sys.executable, "-m", "services.cli", "run", "--task", "match", "--graph", "chain", "--num-objects", "3",
           "--collector", "ppo", "--max-seconds", "45", "--run-dir", str(run_dir), "--router-port", "0",
           "--dashboard-port", "0", "--metrics-base-port", "0", "--progress", "false", "--evaluator-min-interval-s", "2"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=900)  # the post-run CEM evaluation is slow on a loaded machine
    assert done.returncode == 0, done.stdout + done.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    policy = summary["policy"]
    assert policy["published_version"] >= 2 and set(policy["worker_versions"]) == {"0"}
    assert 1 <= policy["worker_versions"]["0"] <= policy["published_version"]
    assert sum(policy["lag_histogram"].values()) > 0 and all(k.isdigit() or k in ("over", "future")
                                                             for k in policy["lag_histogram"])
    published = [v for _, who, v in policy["version_timeline"] if who.startswith("policy-learner")]
    assert published == sorted(published) and published[-1] == policy["published_version"]
    evaluation = summary["evaluation"]
    assert "error" not in evaluation, evaluation
    accuracy = evaluation["prediction"]["colour_accuracy"]
    assert set(accuracy) == {"id", "ood_0.1", "ood_1", "ood_10"}
    assert all(len(v) == 5 and all(0 <= x <= 1 for x in v) for v in accuracy.values())
    match = evaluation["match"]
    assert set(match["returns"]) == {"CEM + CDL", "policy", "random"}
    assert all(set(r) == {"id", "ood_1"} and len(r["id"]) == match["episodes"] for r in match["returns"].values())
    assert match["mean"]["CEM + CDL"]["id"] > match["mean"]["random"]["id"] + 5, match["mean"]
    for png in ("policy.png", "evaluation.png", "graph.png", "learning_curve.png"):
        assert (run_dir / png).read_bytes()[:4] == b"\x89PNG", png
