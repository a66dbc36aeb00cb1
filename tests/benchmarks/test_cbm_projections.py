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
