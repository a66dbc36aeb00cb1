"""Table 7.2's benchmark (benchmarks.dyno_world_model) on the sprite game: episodes that never end
early, seeded; rollouts that start after the context frames; a bad budget refused before any work."""
from __future__ import annotations

import json

import pytest
import torch

from benchmarks import dyno_world_model as bench
from causal.slot_world_model import psnr
from causal.slots import frames_to_tensor
from envs.sprites import SpritesEnv


def test_sprite_episodes_keep_the_agent_alive_and_repeat_from_their_seed() -> None:
    env = SpritesEnv(num_fish=4)
    episodes = bench.sprite_episodes(env, seed=3, count=6, steps=12)
    assert episodes.frames.shape == (6, 13, 32, 32, 3) and episodes.labels.shape == (6, 13, 32, 32)
    assert episodes.actions.shape == (6, 12) and episodes.rewards is not None and episodes.rewards.shape == (6, 12)
    # a dead agent is not drawn: label 1 (the agent) in every frame means no kept episode ended
    assert bool((episodes.labels == 1).flatten(2).any(-1).all())
    assert episodes.dropped >= 0
    again = bench.sprite_episodes(SpritesEnv(num_fish=4), seed=3, count=6, steps=12)
    assert torch.equal(again.frames, episodes.frames) and torch.equal(again.actions, episodes.actions)
    assert again.dropped == episodes.dropped


def test_a_context_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="--context"):
        bench.Budget(context=0)
    assert bench.Budget(context=4, horizon=20).steps == 23


def test_the_sprite_table_scores_twenty_steps_after_the_context(tmp_path, capsys) -> None:
    out = tmp_path / "wm.json"
    bench.main(["--env", "sprites", "--num-objects", "3", "--context", "3", "--train-episodes", "4",
                "--eval-episodes", "3", "--ae-updates", "2", "--slot-updates", "2", "--wm-updates", "2",
                "--out", str(out)])
    record = json.loads(out.read_text())["results"][0]
    assert record["env"] == "sprites" and record["context"] == 3
    rollouts = record["rollouts"]
    assert len(rollouts["slot"]["psnr_per_step"]) == len(rollouts["monolithic"]["psnr_per_step"]) == 20
    # the copy baseline repeats the last context frame (index 2) against frames 3..22
    test = bench.sprite_episodes(SpritesEnv(num_fish=2), bench.EVAL_SEED_OFFSET, 3, 22)
    truth = frames_to_tensor(test.frames[:, 3:].flatten(0, 1)).view(3, 20, 3, 32, 32)
    copy = frames_to_tensor(test.frames[:, 2])[:, None].expand_as(truth)
    expected = psnr(copy, truth).mean(0)
    assert rollouts["copy"]["psnr_per_step"] == pytest.approx(expected.tolist(), rel=1e-5)
    assert record["episodes_dropped"]["eval"] == test.dropped
    assert set(bench.ROWS) <= set(rollouts) and "psnr_objects_last" in rollouts["slot"]
    for name in ("slot", "monolithic"):
        error = rollouts["latent_error"][name]
        assert len(error["rollout"]) == len(error["copy"]) == 20 and min(error["copy"]) >= 0.0
    capsys.readouterr()
    bench.main(["--merge", str(out), str(out)])  # one table over runs written by separate processes
    merged = capsys.readouterr().out
    slot_psnr = rollouts["slot"]["psnr_last"]["mean"]
    assert "over 2 seeds" in merged and f"| slot | {slot_psnr:.2f} +- 0.00 |" in merged


def test_object_psnr_reads_only_the_objects_pixels() -> None:
    truth = torch.zeros(2, 3, 4, 4)
    labels = torch.zeros(2, 4, 4, dtype=torch.long)
    labels[0, 1:3, 1:3] = 2
    images = torch.full_like(truth, 0.5)  # background off by 0.5 ...
    images[0, :, 1:3, 1:3] = 0.1  # ... the object's pixels off by 0.1: 20 dB on them
    got = bench.object_psnr(images, truth, labels)
    assert float(got[0]) == pytest.approx(20.0, rel=1e-5)
    assert bool(got[1].isnan()), "a frame without objects has no objects' PSNR"
    assert float(psnr(images[0], truth[0])) < 10.0, "the full frame is dominated by the background"
