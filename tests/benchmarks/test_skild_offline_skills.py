"""The offline skill-learner benchmark at a toy budget: every variant learns from one pre-training's replay."""
from __future__ import annotations

import json

from benchmarks.skild_offline_skills import markdown, run


def test_variants_learn_from_the_same_replay_and_are_scored_against_random_actions(tmp_path):
    results = run("installing-printer", env_steps=320, seed=0, updates=3, segments=4,
                  variants=["default", "one-target"], target="table -> table", out=tmp_path)
    saved = json.loads((tmp_path / "installing-printer-seed0.json").read_text())
    assert saved["targets"] and "table -> table" in saved["targets"]
    assert [r["target"] for r in results["default"]["rates"]] == saved["targets"]
    assert [r["target"] for r in results["one-target"]["rates"]] == ["table -> table"]
    # the table never moves: its row is induced whatever the policy
    assert results["one-target"]["rates"][0]["skill"] == 1.0
    assert saved["replay_shares"]["table -> table"] == 1.0  # induced on every step of the replay
    text = markdown(results, saved["targets"], saved["replay_shares"])
    assert text.count("\n") == len(saved["targets"]) + 2 and "| random actions |" in text
    assert "| table -> table | 1.0000 |" in text
