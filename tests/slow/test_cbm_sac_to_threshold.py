"""Fig. 4.8's benchmark to a threshold: SAC behind the true minimal abstraction of match-first solves it
in 2,000 env steps and keeps its success with every task-irrelevant factor out of distribution; the
full-state policy learns the task too but loses success out of distribution (the chapter's claim)."""
from __future__ import annotations

import pytest

from benchmarks import cbm_sac_abstraction as bench

pytestmark = pytest.mark.slow

SCENE = dict(graph="full", num_objects=3, distractors="5,5", task="match-first", episode_length=10)
RUN = bench.SACRun(steps=2_000, eval_every=1_000, curve_episodes=10, eval_episodes=50)


def test_the_minimal_abstraction_generalises_and_the_full_state_does_not() -> None:
    minimal = bench.run_condition((SCENE, "cbm_true_reward", [0, 9], RUN, 0))
    assert minimal["id"]["success"] >= 0.9
    assert minimal["ood_all"] == minimal["ood_distractors"] == minimal["id"]
    full = bench.run_condition((SCENE, "full", list(range(22)), RUN, 0))
    assert full["id"]["success"] >= 0.8
    assert full["ood_all"]["success"] <= full["id"]["success"] - 0.2
