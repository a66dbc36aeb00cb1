"""Fig. 5.4's exploration benchmark: tiny real runs of every reward write their curves and plots;
ELDEN's reward waits for its warm-up; bad arguments are refused before anything runs."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import elden_exploration as ex

TINY = dict(env="cleaning-car", env_steps=512, num_envs=4, rollout_steps=32, warmup_steps=256,
            dynamics_updates_per_step=0.1, window=10, log_every=256)
CURVE = {"env_steps", "stages", "success", "intrinsic_mean", "episodes"}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, dict]]:
    out = tmp_path_factory.mktemp("elden-exploration")
    configs = [ex.ExplorationConfig(reward=r, seed=0, **TINY) for r in ex.REWARDS]
    results = ex.main(configs, out, workers=1)
    return out, {r["config"]["reward"]: r for r in results}


def test_every_reward_writes_its_curve_and_plots(tiny: tuple[Path, dict[str, dict]]) -> None:
    out, results = tiny
    assert set(results) == set(ex.REWARDS)
    for reward in ex.REWARDS:
        saved = json.loads((out / f"cleaning-car-{reward}-s0.json").read_text())
        assert (out / f"cleaning-car-{reward}-s0.png").stat().st_size > 1000
        curve = saved["curve"]
        assert set(curve) >= CURVE and len({len(v) for v in curve.values()}) == 1
        assert curve["env_steps"] == [128 * (k + 1) for k in range(4)]
        assert all(0.0 <= s <= 1.0 for s in curve["stages"] + curve["success"])
        assert saved["num_stages"] == 6 and saved["final_stages"] == curve["stages"][-1]
        assert curve["episodes"][-1] >= 4
    assert (out / "cleaning-car-comparison.png").stat().st_size > 1000
    table = (out / "cleaning-car-summary.md").read_text()
    assert all(title in table for title in ("PPO", "ELDEN", "Dynamics curiosity", "Disagreement"))


def test_elden_reward_is_zero_during_warmup_and_not_after(tiny: tuple[Path, dict[str, dict]]) -> None:
    curve = tiny[1]["elden"]["curve"]
    rollout = TINY["num_envs"] * TINY["rollout_steps"]
    seen_before = np.asarray(curve["env_steps"]) - rollout
    bonus = np.asarray(curve["intrinsic_mean"])
    assert (bonus[seen_before < TINY["warmup_steps"]] == 0).all()
    assert (bonus[seen_before >= TINY["warmup_steps"]] > 0).all()


def test_baselines_read_their_own_models_without_warmup(tiny: tuple[Path, dict[str, dict]]) -> None:
    results = tiny[1]
    assert all(v == 0 for v in results["none"]["curve"]["intrinsic_mean"])
    for reward in ("curiosity", "disagreement"):
        bonus = results[reward]["curve"]["intrinsic_mean"]
        assert bonus[0] == 0 and all(b > 0 for b in bonus[1:]), (reward, bonus)


def test_a_seeded_run_repeats() -> None:
    cfg = ex.ExplorationConfig(reward="none", seed=3, **TINY)
    assert ex.run(cfg)["curve"] == ex.run(cfg)["curve"]


@pytest.mark.parametrize("argv, message", [
    (["--envs", "kitchen"], "unknown env 'kitchen'"),
    (["--rewards", "elden", "empowerment"], "unknown reward 'empowerment'"),
    (["--workers", "0"], "--workers must be >= 1"),
    (["--env-steps", "100"], "below one rollout"),
    (["--eta", "-1"], "eta must be >= 0"),
])
def test_bad_arguments_are_refused_before_anything_runs(argv: list[str], message: str, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        ex.parse(argv + ["--out", str(tmp_path / "out")])
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_cli_builds_one_run_per_env_reward_and_seed() -> None:
    configs, out, workers = ex.parse(["--envs", "thawing", "cleaning-car", "--rewards", "none", "elden",
                                      "--seeds", "0", "1", "--workers", "2", "--grad-reg", "1e-2"])
    assert len(configs) == 8 and workers == 2 and {c.grad_reg for c in configs} == {1e-2}
    assert {c.name for c in configs} >= {"thawing-elden-s1", "cleaning-car-none-s0"}
