"""FLAM's Table 8.4 benchmark (behaviour cloning from pseudo-labels) end to end at a toy budget, and
its token labels, clip starts, labelled subsets and refused arguments."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.flam_bc import clip_starts, labelled_subsets, main, parse_args, token_labels

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.mark.parametrize("game", [["--env", "sprites", "--num-fish", "2"],
                                  ["--env", "multigrid", "--num-agents", "2", "--mask-binding", "1"]])
def test_flam_bc_toy_budget(tmp_path: Path, capsys: pytest.CaptureFixture[str], game: list[str]) -> None:
    out = tmp_path / "bc.json"
    main(parse_args([*game, "--transitions", "120", "--labels", "10", "60", "--ae-updates", "1",
                     "--updates", "2", "--slot-dim", "16", "--decoder-updates", "3", "--bc-updates", "3",
                     "--eval-episodes", "1", "--heldout-transitions", "20", "--out", str(out)]))
    results = json.loads(out.read_text())["results"]
    assert set(results) == {"demonstrations", "flam_train_seconds", "labels_10", "labels_60", "all_labels",
                            "expert", "demonstrator", "random"}
    assert results["demonstrations"]["transitions"] >= 120
    for n in (10, 60):
        assert set(results[f"labels_{n}"]) == {"vanilla", "flam", "idm"}
        for name in ("flam", "idm"):
            assert 0.0 <= results[f"labels_{n}"][name]["pseudo_label_accuracy"] <= 1.0
        for name in ("flam", "idm", "vanilla"):
            assert 0.0 <= results[f"labels_{n}"][name]["heldout_action_accuracy"] <= 1.0
    assert results["expert"]["return_mean"] >= 0.0 and results["random"]["episodes"] == 1
    assert f"Table 8.4 analogue ({game[1]}" in capsys.readouterr().out


def test_token_labels_take_the_object_with_most_pixels_over_the_background() -> None:
    labels = np.zeros((1, 8, 8), np.uint8)
    labels[0, 3, 3] = 2  # one pixel of object 2 in token 0: it wins over 15 background pixels
    labels[0, 0:4, 4:8] = 1
    labels[0, 0, 4] = 3  # token 1: 15 pixels of object 1 beat object 3's one
    assert token_labels(labels).tolist() == [[2, 1, 0, 0]]


def test_clip_starts_stay_inside_episodes_and_subsets_nest() -> None:
    episode_of_frame = np.array([0, 0, 0, 1, 1, 1, 1, 2, 2])
    assert clip_starts(episode_of_frame, 3).tolist() == [0, 3, 4]
    subsets = labelled_subsets(100, (10, 40), seed=0)
    assert torch.equal(subsets[40][:10], subsets[10]) and len(set(subsets[40].tolist())) == 40


def test_bad_arguments_are_refused_before_anything_runs(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse_args(["--transitions", "100", "--labels", "200"])
    assert "--labels must lie in 1..--transitions" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_args(["--epsilon", "2"])
    with pytest.raises(SystemExit):
        parse_args(["--seed", "10"])
    assert "--seed must be in 0..9" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_args(["--env", "multigrid", "--num-agents", "10"])
    assert "--env multigrid: num_agents must be at most 9" in capsys.readouterr().err
