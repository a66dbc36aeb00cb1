"""``causeway run --method skild --env installing-printer`` end to end: a real router and real service
processes; the policy-learner pre-trains skills from the workers' SkillBatches and their induced graphs,
switches to task learning at the budget, and the summary carries the task block, SkiLD's phases and the
induced-graph coverage of both phases."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]


def _run(run_dir: Path, *flags: str) -> dict:
    cmd = [sys.executable, "-m", "services.cli", "run", "--method", "skild", "--env", "installing-printer",
           "--policy-skill-learning-starts", "256", "--worker-batch-steps", "128", "--run-dir", str(run_dir),
           "--router-port", "0", "--dashboard-port", "0", "--metrics-base-port", "0", "--progress", "false", *flags]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    return json.loads((run_dir / "summary.json").read_text())


def _check(summary: dict, pretrain: int) -> None:
    skild = summary["skild"]
    assert skild["phase"] == "task" and skild["pretrain_steps"] >= pretrain and skild["task_steps"] > 0, skild
    assert skild["targets"] >= 1 and skild["updates"] > 0 and skild["task_updates"] >= 1, skild
    assert set(summary["task"]) >= {"success_rate", "return_mean", "stages_mean", "episodes"}, summary["task"]
    coverage = summary["induced_coverage"]
    assert coverage["pretrain"]["episodes"] >= 1 and coverage["pretrain"]["rows"], coverage
    assert all(0 < share <= 1 for block in coverage.values() for share in block["rows"].values())
    assert all("->" in row for row in coverage["pretrain"]["rows"])


def test_true_graphs_pretrain_then_task(tmp_path: Path) -> None:
    """The chapter's ablation (the simulator's local graphs): fast enough for every run of the suite. The
    workers are throttled so that on a loaded 2-core machine the learner's owed pre-training updates and
    the first task update fit inside the env-step budget (unthrottled, one loaded core ran the whole
    budget before the switch)."""
    summary = _run(tmp_path / "true", "--policy-skild-graphs", "true", "--max-env-steps", "2400",
                   "--policy-skild-pretrain-steps", "700", "--worker-max-steps-per-second", "200",
                   "--max-seconds", "240")
    assert summary["stopped_because"].startswith("env step budget"), summary["stopped_because"]
    _check(summary, 700)


@pytest.mark.slow
def test_evaluator_graphs_pretrain_then_task(tmp_path: Path) -> None:
    """Induced graphs from the graph-evaluator (pCMI of the dynamics-learner's model) over the bus; the
    workers are throttled so the model exists before most of the budget is spent."""
    summary = _run(tmp_path / "pcmi", "--max-env-steps", "9000", "--policy-skild-pretrain-steps", "3000",
                   "--learner-warmup-steps", "500", "--learner-publish-every-s", "2",
                   "--worker-max-steps-per-second", "250", "--max-seconds", "300")
    _check(summary, 3000)
