"""The chaos benchmark's table (benchmarks/bench_chaos.py): runs' lines from summaries, kills' figures,
the slowdown against the baseline, the markdown."""
from __future__ import annotations

import pytest

from benchmarks.bench_chaos import build_table, format_table, run_row


def summary(stopped: str, lost: tuple[int, int] = (0, 0)) -> dict:
    return {"stopped_because": stopped, "env_steps": 18_000, "updates": 900, "restarts": 6, "f1": 1.0,
            "transitions_lost": {"batches": lost[0], "steps": lost[1]}}


def test_a_runs_line_says_whether_it_reached_its_target() -> None:
    row = run_row(summary("target f1 1.0 reached", (3, 768)), 201.26)
    assert row["target_reached"] and row["seconds"] == 201.3 and (row["lost_batches"], row["lost_steps"]) == (3, 768)
    assert not run_row(summary("max_seconds 900 reached"), 900.0)["target_reached"]
    missing = run_row({}, 12.0)
    assert missing["stopped_because"] == "no summary" and not missing["target_reached"] and missing["lost_steps"] == 0


KILLS = [{"service": "env-worker-0", "back_on_bus_s": 12.5, "run_recovered_s": 14.0, "learner_counted_lost_steps": 0,
          "transitions_lost_at_least": 120, "restarts": 1, "killed_at": 1.0},
         {"service": "dynamics-learner", "back_on_bus_s": 15.0, "run_recovered_s": 17.5,
          "learner_counted_lost_steps": 1536, "transitions_lost": 1280},
         {"service": "dashboard", "note": "not killed: the run had ended"},
         {"service": "supervisor", "services_gone_s": 61.0, "left_running_60s_after": ["env-worker-0"],
          "back_on_bus_s": 40.0, "run_recovered_s": 55.0}]


def test_the_table_keeps_the_kill_figures_and_the_slowdown() -> None:
    base, chaos = run_row(summary("target f1 1.0 reached"), 200.0), run_row(summary("target f1 1.0 reached", (6, 1536)), 260.0)
    result = build_table(base, chaos, KILLS)
    assert [k["killed"] for k in result["kills"]] == ["env-worker-0", "dynamics-learner", "dashboard", "supervisor"]
    assert "killed_at" not in result["kills"][0] and "restarts" not in result["kills"][0]
    assert result["kills"][1]["learner_counted_lost_steps"] == 1536
    assert result["slowdown"] == pytest.approx(1.3) and result["extra_seconds"] == pytest.approx(60.0)
    text = format_table(result)
    assert "| dynamics-learner | 15.0 | 17.5 | 1,536 | not in the resumed checkpoint: 1,280 steps |" in text
    assert "| dashboard | - | - | - | not killed: the run had ended |" in text
    assert "| supervisor | 40.0 | 55.0 | - | still running 60 s after the supervisor's SIGKILL: env-worker-0 |" in text
    assert "| chaos | 260.0 | target f1 1.0 reached | 18,000 | 900 | 6 | 6 / 1,536 |" in text
    assert "+60.0 s (1.3x the baseline)" in text


@pytest.mark.parametrize("baseline_stop, chaos_stop", [("max_seconds 900 reached", "target f1 1.0 reached"),
                                                       ("target f1 1.0 reached", "max_seconds 900 reached")])
def test_no_slowdown_unless_both_runs_reached_the_target(baseline_stop: str, chaos_stop: str) -> None:
    result = build_table(run_row(summary(baseline_stop), 900.0), run_row(summary(chaos_stop), 300.0), KILLS)
    assert result["slowdown"] is None and result["extra_seconds"] is None
    assert "baseline)" not in format_table(result)


def test_without_a_baseline_only_the_chaos_run_is_listed() -> None:
    result = build_table(None, run_row(summary("target f1 1.0 reached"), 250.0), KILLS)
    assert result["slowdown"] is None and "| baseline |" not in format_table(result)
