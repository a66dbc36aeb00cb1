"""The Fig. 6.4 benchmark end to end at a toy budget: coverage, and each target's skill against random actions."""
from __future__ import annotations

import json

from benchmarks.skild_coverage import main
from causal.skild import SkiLDConfig
from causal.skild_agent import SkillLearnerConfig


def test_coverage_and_per_target_hit_rates_are_written(tmp_path):
    main("installing-printer", env_steps=320, seeds=[0], episodes=4, episode_length=30, out=tmp_path,
         methods=("skild", "random"), learner=SkillLearnerConfig(hidden=32, batch_size=32, learning_starts=64),
         cfg=SkiLDConfig(eligible_after=5, relabel_horizon=5), target_segments=16)
    saved = json.loads((tmp_path / "installing-printer.json").read_text())
    assert saved["relabel_horizon"] == 5 and saved["n_step"] == 1
    rates = saved["budget"]["skild"]["target_rates"][0]
    assert len(rates) == saved["budget"]["skild"]["targets"][0] >= 1
    assert all(r["segments"] == 16 and 0 <= r["skill"] <= 1 and 0 <= r["random"] <= 1 for r in rates)
    text = (tmp_path / "installing-printer.md").read_text()
    assert "| SkiLD target | seeds |" in text and rates[0]["target"] in text
