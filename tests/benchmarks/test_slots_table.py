"""The Table 7.1 benchmark end to end at a toy budget: every variant is trained and scored."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from benchmarks.slots_table import VARIANTS, Budget, frame_source, main
from envs.chemical_pixels import PART_COLOR


def test_slots_table_toy_budget(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "table.json"
    main(["--seeds", "0", "--num-objects", "2", "--frame-size", "16", "--train-frames", "16", "--eval-frames", "8",
          "--ae-updates", "1", "--slot-updates", "2", "--out", str(out)])
    result = json.loads(out.read_text())["results"][0]
    for variant in VARIANTS:
        assert -1.0 <= result[variant]["slots"]["fg_ari"] <= 1.0
        assert 0.0 <= result[variant]["slot_identity"] <= 1.0
    assert "fg_ari_with_masks" in result["always"] and "fg_ari_with_masks" not in result["none"]
    printed = capsys.readouterr().out
    assert all(f"| {variant} |" in printed for variant in VARIANTS)


def test_slots_table_on_the_sprite_game(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "table.json"
    main(["--env", "sprites", "--seeds", "1", "--num-objects", "3", "--frame-size", "32", "--train-frames", "16",
          "--eval-frames", "8", "--ae-updates", "1", "--slot-updates", "2", "--out", str(out)])
    result = json.loads(out.read_text())["results"][0]
    assert result["env"] == "sprites"
    for variant in VARIANTS:
        assert -1.0 <= result[variant]["slots"]["fg_ari"] <= 1.0
    with pytest.raises(ValueError, match="num-objects"):
        main(["--env", "sprites", "--num-objects", "1", "--out", str(tmp_path / "bad.json")])


def test_the_two_tone_scene_draws_the_same_objects_with_grey_lower_halves() -> None:
    budget = Budget(num_objects=3, frame_size=32)
    plain, plain_labels = frame_source("chemical-pixels", budget)(4, 6)
    toned, labels = frame_source("chemical-pixels-two-tone", budget)(4, 6)
    assert torch.equal(labels, plain_labels) and not toned[labels == 0].any()
    part = torch.as_tensor(PART_COLOR)
    grey = (toned == part).all(dim=-1)
    assert 0.3 < float(grey[labels > 0].float().mean()) < 0.7 and not grey[labels == 0].any()
    assert not (plain == part).all(dim=-1).any()
    assert torch.equal(toned[~grey], plain[~grey])


def test_more_slots_than_segments_leaves_the_spare_slots_free(tmp_path: Path) -> None:
    """``--num-slots`` above the segments (the chapter's K): every variant trains and scores, matched
    masks included; a K below one per object and the background fails before any frame is made."""
    out = tmp_path / "table.json"
    main(["--seeds", "0", "--num-objects", "2", "--num-slots", "6", "--frame-size", "16", "--train-frames", "16",
          "--eval-frames", "8", "--ae-updates", "1", "--slot-updates", "3", "--mask-assignment", "matched",
          "--out", str(out)])
    result = json.loads(out.read_text())["results"][0]
    assert result["num_slots"] == 6
    for variant in VARIANTS:
        assert -1.0 <= result[variant]["slots"]["fg_ari"] <= 1.0
    with pytest.raises(ValueError, match="num-slots 2 < 3"):
        main(["--num-objects", "2", "--num-slots", "2", "--out", str(tmp_path / "bad.json")])
    assert not (tmp_path / "bad.json").exists()


def test_the_binding_weight_reaches_the_masked_variants_and_is_refused_below_zero(tmp_path: Path) -> None:
    out = tmp_path / "table.json"
    main(["--seeds", "0", "--num-objects", "2", "--frame-size", "16", "--train-frames", "16", "--eval-frames", "8",
          "--ae-updates", "1", "--slot-updates", "2", "--mask-binding", "0.5", "--variants", "always", "none",
          "--out", str(out)])
    result = json.loads(out.read_text())["results"][0]
    assert result["mask_binding"] == 0.5
    assert "mask_binding_ce" in result["always"]["final_losses"]  # masks given: the term is computed
    assert "mask_binding_ce" not in result["none"]["final_losses"]
    with pytest.raises(SystemExit):
        main(["--mask-binding", "-1", "--out", str(tmp_path / "bad.json")])
    assert not (tmp_path / "bad.json").exists()
