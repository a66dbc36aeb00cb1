"""Table 5.2's ablation benchmark: each variant is a real switch of the trainer, results accumulate."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from benchmarks import elden_ablation
from causal.elden import ELDENConfig


@pytest.fixture(scope="module")
def thawing_data() -> tuple:
    return elden_ablation.collect("thawing", 400, seed=0)


def test_every_variant_is_a_valid_config_and_has_a_row() -> None:
    for name, overrides in elden_ablation.VARIANTS.items():
        if name == elden_ablation.PCMI:  # CDL's model, not an ELDEN switch
            assert overrides == {} and name in elden_ablation.TABLE_ROWS
            continue
        cfg = dataclasses.replace(ELDENConfig(), **overrides)
        assert name in elden_ablation.TABLE_ROWS
        assert cfg.mixup == (name not in ("no-mixup-no-reg", "no-mixup", *elden_ablation.MASK_VARIANTS))
    assert elden_ablation.VARIANTS["lambda-0"]["grad_reg"] == 0.0
    for env, rows in elden_ablation.CHAPTER.items():
        assert set(rows) <= set(elden_ablation.VARIANTS), env
    assert set(elden_ablation.CHAPTER) == {"thawing", "cleaning-car", "manipulation"}


def test_collection_is_the_envs_own_transitions(thawing_data: tuple) -> None:
    state, action, next_state, layout = thawing_data
    assert state.shape == next_state.shape == (400, layout.num_factors)
    assert action.shape == (400, 1) and set(np.unique(action)) <= set(range(layout.action_width))
    again = elden_ablation.collect("thawing", 400, seed=0)
    np.testing.assert_array_equal(state, again[0])


def test_the_switches_reach_the_trainer_and_only_they_differ(thawing_data: tuple) -> None:
    *data, layout = thawing_data
    trained = {}
    for variant in ("no-mixup-no-reg", "lambda-0", "lambda-1e-1"):
        cfg = dataclasses.replace(ELDENConfig(members=2, member_batch=8), **elden_ablation.VARIANTS[variant])
        trainer, stats = elden_ablation.train(layout, cfg, tuple(data), updates=2, seed=3)
        trained[variant] = (trainer, stats)
    assert not trained["no-mixup-no-reg"][0].uses_mixup and trained["lambda-0"][0].uses_mixup
    assert "grad_penalty" not in trained["lambda-0"][1] and trained["lambda-1e-1"][1]["grad_penalty"] > 0
    same, _ = elden_ablation.train(layout, trained["lambda-0"][0].cfg, tuple(data), updates=2, seed=3)
    for name, value in same.model.state_dict().items():
        torch.testing.assert_close(value, trained["lambda-0"][0].model.state_dict()[name])
    mixed = trained["lambda-0"][0].model.token_w1
    assert not torch.equal(mixed, trained["no-mixup-no-reg"][0].model.token_w1)
    assert not torch.equal(mixed, trained["lambda-1e-1"][0].model.token_w1)


def test_main_scores_each_variant_and_a_rerun_replaces_its_entry(tmp_path, capsys) -> None:
    argv = ["--variants", "lambda-0", "no-mixup-no-reg", "--updates", "1", "--transitions", "200",
            "--episodes", "2", "--out", str(tmp_path)]
    elden_ablation.main(argv)
    elden_ablation.main(argv[:2] + argv[3:])
    results = json.loads((tmp_path / "elden-ablation.json").read_text())
    assert sorted(r["variant"] for r in results) == ["lambda-0", "no-mixup-no-reg"]
    for r in results:
        assert set(r["estimators"]) == {"jacobian", "attention"}
        assert 0.0 <= r["estimators"]["jacobian"]["roc_auc"] <= 1.0
    printed = capsys.readouterr()
    assert "| no Reg, i.e. lambda = 0 | thawing | 1 |" in printed.out
    assert "thawing seed 0: collecting 200 transitions" in printed.err       # progress, on stderr
    assert "thawing seed 0 lambda-0: update 1 of 1 (" in printed.err


def test_a_mask_baseline_trains_its_own_model_and_is_scored_by_its_mask(tmp_path, capsys) -> None:
    elden_ablation.main(["--variants", "input-mask", "attention-mask", "--updates", "1", "--transitions", "200",
                         "--episodes", "2", "--out", str(tmp_path)])
    results = {r["variant"]: r for r in json.loads((tmp_path / "elden-ablation.json").read_text())}
    for variant, kind in (("input-mask", "input"), ("attention-mask", "attention")):
        assert set(results[variant]["estimators"]) == {variant}
        assert results[variant]["config"]["mask"]["kind"] == kind
        assert 0.0 <= results[variant]["estimators"][variant]["roc_auc"] <= 1.0
    out = capsys.readouterr().out
    assert "| Input Mask (Table 5.1) | thawing | 1 |" in out and "| 0.50 / 0.40 |" in out


def test_bad_budgets_are_refused_before_anything_runs(tmp_path) -> None:
    with pytest.raises(SystemExit):
        elden_ablation.main(["--updates", "0", "--out", str(tmp_path)])
    assert not (tmp_path / "elden-ablation.json").exists()


def test_pcmi_trains_cdl_on_the_same_transitions_and_is_scored_by_point_wise_cmi(tmp_path, capsys) -> None:
    """Table 5.1's pCMI row on the ELDEN variants' data: CDL drawing as many transitions as ELDEN
    (2 updates x 5 members x 32 = 320 rows: 5 updates of 64), its own estimator scored."""
    elden_ablation.main(["--variants", "pcmi", "lambda-0", "--updates", "2", "--transitions", "200",
                         "--episodes", "2", "--out", str(tmp_path)])
    results = {r["variant"]: r for r in json.loads((tmp_path / "elden-ablation.json").read_text())}
    pcmi = results["pcmi"]
    assert pcmi["cdl_updates"] == 5 and pcmi["transitions"] == results["lambda-0"]["transitions"] == 200
    assert set(pcmi["estimators"]) == {"pcmi"} and 0.0 <= pcmi["estimators"]["pcmi"]["roc_auc"] <= 1.0
    assert (tmp_path / "thawing-s0-pcmi-u2-t200.pt").exists()
    out = capsys.readouterr().out
    assert "| pCMI (CDL, Table 5.1) | thawing | 1 |" in out and "| 0.55 / 0.60 |" in out
