"""The controllable-distractors probe (issue 19): its scores on a hand-made CMI matrix, a short run's
output, and bad input refused."""
import json

import numpy as np
import pytest

from benchmarks.cbm_projections import main, scores

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_scores_count_only_the_off_diagonal_distractor_entries():
    cmi = np.zeros((3, 4))
    cmi[0, 1], cmi[2, 0], cmi[1, 2] = 0.05, 0.02, 0.019  # two at or above 0.02, one below
    cmi[[0, 1, 2], [0, 1, 2]] = 0.5  # self entries: not edges between distractors
    cmi[:, 3] = [1.0, 2.0, 3.0]  # the action
    out = scores(cmi, 3, 0.02)
    assert out["cd_cd_edges"] == 2 and out["of"] == 6
    assert out["cd_cd_max"] == pytest.approx(0.05)
    assert out["self_mean"] == pytest.approx(0.5) and out["action_mean"] == pytest.approx(2.0)


def test_a_short_run_writes_its_trace(tmp_path, capsys):
    main(["--controllable", "4", "--action-dim", "2", "--steps", "400", "--updates", "20", "--estimate-every", "10",
          "--target", "next", "--out", str(tmp_path)])
    data = json.loads((tmp_path / "projections.json").read_text())
    assert [row["update"] for row in data["trace"]] == [10, 20]
    assert np.array(data["cmi"]).shape == (4, 5)
    assert data["args"]["target"] == "next"
    assert len(capsys.readouterr().out.strip().splitlines()) == 2


def test_bad_input_is_refused_before_anything_runs(tmp_path):
    with pytest.raises(SystemExit):
        main(["--controllable", "1", "--out", str(tmp_path)])
    assert not (tmp_path / "projections.json").exists()


def test_static_and_uncontrollable_rows_count_every_input_but_their_own():
    cmi = np.zeros((4, 5))  # 2 controllable, 1 uncontrollable, 1 static; the action last
    cmi[2, 2], cmi[3, 3] = 0.9, 0.9  # each row's own factor: never counted
    cmi[2, 4], cmi[3, 0], cmi[3, 4] = 0.03, 0.05, 0.01
    out = scores(cmi, 2, 0.02, uncontrollable=1, static=1)
    assert (out["ud_edges"], out["ud_of"], out["static_edges"], out["static_of"]) == (1, 4, 1, 4)
    assert out["static_max"] == pytest.approx(0.05)


def test_static_factors_keep_their_episode_value(tmp_path):
    main(["--controllable", "3", "--uncontrollable", "1", "--static", "2", "--action-dim", "2", "--steps", "60",
          "--episode-length", "20", "--updates", "4", "--estimate-every", "2", "--out", str(tmp_path)])
    data = json.loads((tmp_path / "projections.json").read_text())
    assert np.array(data["cmi"]).shape == (6, 7)
    assert {"ud_edges", "static_edges"} <= set(data["trace"][-1])
    from benchmarks.cbm_projections import collect
    from envs.distractors import Distractors

    state, _, nxt = collect(Distractors(3, 1, "continuous", 2, seed=0), 2, 60, 20, 0.0, np.random.default_rng(0), 2)
    np.testing.assert_array_equal(nxt[:, 4:], state[:, 4:])  # x' = x
    starts = state[::20, 4:]
    assert len({tuple(row.tolist()) for row in starts}) == 3  # a new value each episode
    assert bool((state[:20, 4:] == state[0, 4:]).all())
