"""Table 4.1's benchmark on the block and tool-use scenes: their collection data (4-D actions, the
scripted grasp or Series solution that makes the cubes and the tool move) and the truth it scores against."""
from __future__ import annotations

from pathlib import Path

from benchmarks.cbm_graph_table import collect
from envs.block import PICK_HEIGHT
from envs.manipulation_layout import MOV_HALF, TABLE_TOP


def test_block_collection_opens_with_a_grasp_of_mov1() -> None:
    spec, data = collect(dict(distractors="2,1", task="pick", episode_length=40), 45, 0, "block")
    assert spec.env_id == "block" and spec.num_factors == 17 + 3 and spec.reward_parents is not None
    assert data["state"].shape == (45, 20) and data["action"].shape == (45, 4) and not data["heldout"].any()
    first = data["next_state"][:40, 7]
    assert first.max() >= TABLE_TOP[2] + MOV_HALF + PICK_HEIGHT  # the opening grasp lifted mov1 (success)
    assert data["reward"][:40].max() == 1.0


def test_block_grasps_can_take_every_movable_cube(monkeypatch) -> None:
    """``--grasp all``: each scripted opening grasps one of mov1-mov3, drawn per episode; the default
    grasps mov1 and draws nothing (its random stream is the one the tables were measured with)."""
    import pytest

    import envs.skills
    from benchmarks.cbm_graph_table import BLOCK_CUBES, CollectionPolicy

    grasped: list[str] = []
    real = envs.skills.grasp
    monkeypatch.setattr(envs.skills, "grasp", lambda obj, **kw: grasped.append(obj) or real(obj, **kw))
    default = CollectionPolicy(None, "block", seed=3)
    before = default.rng.bit_generator.state
    for _ in range(4):
        default.start_episode()
    assert default.rng.bit_generator.state == before and grasped == ["mov1", "mov1"]
    grasped.clear()
    every = CollectionPolicy(None, "block", seed=3, grasp_targets=BLOCK_CUBES)
    for _ in range(40):
        every.start_episode()
    assert len(grasped) == 20 and set(grasped) == set(BLOCK_CUBES)  # every other episode, each cube
    with pytest.raises(ValueError, match="grasp_targets"):
        CollectionPolicy(None, "block", seed=0, grasp_targets=("unm",))


def test_block_collection_can_grasp_mov2() -> None:
    spec, data = collect(dict(distractors="0,0", task="pick", episode_length=40), 40, 1, "block", ("mov2",))
    mov2_z = spec.factor_names.index("mov2.z")
    assert data["next_state"][:, mov2_z].max() > TABLE_TOP[2] + MOV_HALF + 0.02  # the opening grasp lifted mov2


def test_tool_use_collection_opens_with_the_scripted_series() -> None:
    from envs.manipulation_layout import TOOL_USE
    from envs.tool_use import IN_REACH_X

    spec, data = collect(dict(distractors="1,1", task="series", episode_length=90), 90, 0, "tool-use")
    assert spec.env_id == "tool-use" and spec.num_factors == 15 + 2 and data["state"].shape == (90, 17)
    tool_z, block_x = TOOL_USE.factor_slice("tool").start + 2, TOOL_USE.factor_slice("block").start
    assert data["next_state"][:, tool_z].max() > TABLE_TOP[2] + 0.05  # the tool lifted over the block
    assert data["state"][0, block_x] > 0.25 and data["next_state"][-1, block_x] <= IN_REACH_X  # and pulled it in


def test_runs_of_single_seeds_merge_into_one_table(tmp_path: Path) -> None:
    import json

    import pytest

    from benchmarks.cbm_graph_table import main, merge_tables

    def run(seed: int, names: list[str]) -> Path:
        row = {"graph": {k: 0.5 + seed / 10 for k in ("accuracy", "with_self_accuracy", "empty_with_self_accuracy",
                                                      "f1", "non_distractor_f1")},
               "reward": {"f1": 1.0, "accuracy": 1.0}, "abstraction_accuracy": 1.0,
               "abstraction_accuracy_true_reward": 1.0, "cdl_abstraction_accuracy": 0.5, "seconds_per_update": 0.1}
        path = tmp_path / f"s{seed}.json"
        path.write_text(json.dumps({"args": {"seeds": [seed]}, "factor_names": names,
                                    "rows": [{"variant": v, "seed": seed, **row} for v in ("implicit", "explicit")]}))
        return path

    paths = [run(1, ["a"]), run(0, ["a"])]
    merged = merge_tables(paths)
    assert [(r["variant"], r["seed"]) for r in merged["rows"]] == [("implicit", 0), ("implicit", 1),
                                                                    ("explicit", 0), ("explicit", 1)]
    main(["--merge", *map(str, paths), "--out", str(tmp_path / "merged")])
    assert json.loads((tmp_path / "merged" / "cbm_table.json").read_text())["rows"] == merged["rows"]
    with pytest.raises(ValueError, match="twice"):
        merge_tables([paths[0], paths[0]])
    with pytest.raises(ValueError, match="different factors"):
        merge_tables([paths[0], run(2, ["b"])])


def test_distractor_errors_are_counted_by_the_kinds_they_join() -> None:
    import numpy as np

    from benchmarks.cbm_graph_table import distractor_errors_by_kind

    names = ("eef.x", "mov1.x", "cd.0", "cd.1", "ud.0")
    truth = np.eye(5, 6, dtype=np.uint8)
    truth[:4, 5] = 1  # the scene and the controllable distractors read the action
    learned = truth.copy()
    learned[0, 2] = learned[1, 3] = 1  # scene <- cd, twice: each makes that cd an ancestor of the scene
    learned[2, 3] = 1  # cd <- cd
    learned[4, 1] = 1  # ud <- scene
    learned[3, 5] = 0  # a missed cd <- action
    learned[0, 1] = 1  # a scene error: not a distractor's
    assert distractor_errors_by_kind(learned, truth, names) == {
        "cd <- action": 1, "cd <- cd": 1, "scene <- cd": 2, "ud <- scene": 1}


def test_the_explicit_variant_takes_the_label_unless_told_otherwise(tmp_path: Path) -> None:
    """``--target`` is both variants' label; ``--explicit-target delta`` keeps CDL's own model (changes)
    beside implicit next values, as the explicit rows measured before the option were."""
    import json

    from benchmarks.cbm_graph_table import main

    small = ["--num-objects", "2", "--distractors", "1,1", "--steps", "120", "--updates", "2", "--estimate-every", "1",
             "--extra-negatives", "--seeds", "0", "--target", "next"]
    main([*small, "--variants", "explicit", "--out", str(tmp_path / "same")])
    main([*small, "--variants", "implicit", "explicit", "--explicit-target", "delta", "--out", str(tmp_path / "cdl")])
    same = json.loads((tmp_path / "same" / "cbm_table.json").read_text())["rows"]
    cdl = json.loads((tmp_path / "cdl" / "cbm_table.json").read_text())["rows"]
    assert [(r["variant"], r["target"]) for r in same] == [("explicit", "next")]
    assert [(r["variant"], r["target"]) for r in cdl] == [("implicit", "next"), ("explicit", "delta")]


def test_settings_the_model_would_refuse_are_refused_before_collection(tmp_path: Path) -> None:
    import pytest

    from benchmarks.cbm_graph_table import main

    for bad in (["--l2", "-1"], ["--lr", "nan"]):
        with pytest.raises(SystemExit):
            main(["--env", "block", "--steps", "10000", *bad, "--out", str(tmp_path)])
    assert not (tmp_path / "cbm_table.json").exists()


def test_the_fdr_rule_keeps_only_edges_shown_above_the_threshold() -> None:
    """``--fdr``: on one estimate, an entry estimated over 0.02 nats but within its noise of it is an
    edge by the fixed threshold only; one far above it by both; the abstraction follows the graph."""
    import numpy as np

    from benchmarks.cbm_graph_table import fdr_scores
    from causal.edge_tests import EdgeEstimate
    from envs.registry import make_env

    spec = make_env("chemical-distractors", num_objects=2, distractors="1,1", task="match").env_spec()
    names = list(spec.factor_names)
    cmi = np.zeros(spec.global_graph.shape)
    stderr = np.full(cmi.shape, 1e-3)
    truth = spec.global_graph.astype(bool) & ~np.eye(*cmi.shape, dtype=bool)
    cmi[truth] = 0.3                                   # every true edge, far above the threshold
    noisy = (names.index("obj0.color"), names.index("cd.0"))  # obj0.color is a reward parent
    cmi[noisy], stderr[noisy] = 0.03, 0.02            # over 0.02 nats, but half a standard error over it
    result = fdr_scores(EdgeEstimate(cmi, stderr, 1000), spec.reward_parents, spec, 0.02, 0.05, 0.02)
    assert result["fixed_threshold_edges"] == int(truth.sum()) + 1
    assert result["edges"] == int(truth.sum())
    assert result["graph"]["accuracy"] == 1.0 and result["fixed_threshold_graph"]["accuracy"] < 1.0
    assert result["abstraction_accuracy_true_reward"] == 1.0
    assert result["fixed_threshold_abstraction_accuracy_true_reward"] < 1.0   # the spurious edge keeps cd.0


def test_fdr_graphs_are_subsets_of_the_thresholds_on_the_same_estimate(tmp_path: Path) -> None:
    import json

    import pytest

    from benchmarks.cbm_graph_table import main

    main(["--num-objects", "2", "--distractors", "1,1", "--steps", "600", "--updates", "2", "--estimate-every", "1",
          "--extra-negatives", "--seeds", "0", "--fdr", "0.05", "--out", str(tmp_path / "run")])
    rows = json.loads((tmp_path / "run" / "cbm_table.json").read_text())["rows"]
    assert [r["variant"] for r in rows] == ["implicit", "explicit"]
    for row in rows:
        fdr = row["fdr"]
        assert fdr["min_cmi"] == 0.02 and fdr["samples"] > 0
        assert fdr["edges"] <= fdr["fixed_threshold_edges"]   # CMI > 0.02 shown implies CMI > 0.02
        assert 0.0 <= fdr["abstraction_accuracy_true_reward"] <= 1.0
    for bad in (["--fdr", "1.5"], ["--fdr", "0.05", "--fdr-min-cmi", "-1"], ["--fdr", "0.05", "--reward-only"]):
        with pytest.raises(SystemExit):
            main(["--env", "block", "--steps", "10000", *bad, "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad" / "cbm_table.json").exists()
