import numpy as np
import pytest

from benchmarks.cbm_scene_edges import edges_only_in, main, moved_share, scene_scores

NAMES = ("a.x", "b.x", "cd.0")


def _cmi(edges):
    cmi = np.zeros((3, 4))
    for i, j in edges:
        cmi[i, j] = 0.5
    return cmi


def test_scene_scores_count_only_non_distractor_off_diagonal_entries():
    truth = np.zeros((3, 4), bool)
    truth[0, 1] = truth[1, 0] = truth[1, 3] = True  # b <- a, a <- b, b <- action
    cmi = _cmi([(0, 1), (1, 3), (0, 3), (2, 0), (0, 2)])  # two right, a <- action wrong, two via cd ignored
    s = scene_scores(cmi, truth, NAMES)
    assert (s["true"], s["tp"], s["fp"], s["fn"]) == (3, 2, 1, 1)
    assert s["precision"] == pytest.approx(2 / 3) and s["recall"] == pytest.approx(2 / 3)


def test_edges_only_in_names_effect_and_cause_and_skips_distractors():
    a, b = _cmi([(0, 1), (1, 3), (2, 0)]), _cmi([(0, 1)])
    assert edges_only_in(a, b, NAMES) == ["b.x<-action"]
    assert edges_only_in(b, a, NAMES) == []


def test_moved_share_per_body():
    names = ("p.x", "p.y", "p.z", "q.x", "q.y", "q.z")
    state = np.zeros((4, 6))
    nxt = state.copy()
    nxt[0, 1] = 0.01  # p moves once
    nxt[1, 5] = 0.0005  # below the tolerance
    nxt[2, 3] = nxt[3, 4] = -0.02  # q moves twice
    assert moved_share({"state": state, "next_state": nxt}, names, ("p", "q")) == {"p": 0.25, "q": 0.5}


def test_the_command_refuses_missing_input(tmp_path):
    with pytest.raises(SystemExit):
        main([])
    with pytest.raises(SystemExit):
        main(["--tables", str(tmp_path / "nothing.json")])
