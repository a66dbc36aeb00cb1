"""The pixels-vs-state comparison scores both runs on the same object graph."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.pixels_vs_state import collapse, compare, object_scores


def _state_summary() -> dict:
    names = ["obj0.color", "obj0.x", "obj1.color", "obj1.x", "action"]
    truth = np.zeros((4, 5), int)
    truth[np.arange(4), np.arange(4)] = 1
    truth[2, 0] = truth[0, 4] = truth[2, 4] = 1  # obj0.color -> obj1.color; the action -> both colours
    cmi = 0.001 * np.ones((4, 5))
    cmi[2, 0], cmi[0, 4], cmi[2, 4] = 0.3, 0.2, 0.05
    cmi[0, 3] = 0.01  # obj1.x -> obj0.color: a weak spurious score
    graph = {"factor_names": names, "cmi": cmi.tolist(), "true_graph": truth.tolist(), "threshold": 0.02}
    return {**graph, "final_graph": dict(graph), "env_steps": 10, "updates": 2}


def test_collapse_takes_the_largest_score_between_objects() -> None:
    summary = _state_summary()
    cmi, objects = collapse(np.asarray(summary["cmi"]), summary["factor_names"])
    assert objects == ["obj0", "obj1"]
    assert np.allclose(cmi, [[0.001, 0.01, 0.2], [0.3, 0.001, 0.05]])


def test_state_and_slot_runs_score_alike() -> None:
    state = _state_summary()
    slot_truth = [[1, 0, 0, 0], [0, 1, 0, 1], [0, 1, 1, 1]]  # background, obj0, obj1, action
    slot_cmi = [[0.5, 0.4, 0.4, 0.4], [0.0, 0.1, 0.01, 0.2], [0.0, 0.3, 0.1, 0.05]]
    pixels = {"factor_names": ["background", "obj0", "obj1", "action"], "cmi": slot_cmi, "true_graph": slot_truth,
              "threshold": 0.02, "slots": {"fg_ari": 0.9}}
    assert object_scores(pixels, 0.02) == object_scores(state, 0.02)  # background dropped: the same object graph
    scores = object_scores(state, 0.02)
    assert scores["objects"] == ["obj0", "obj1"] and scores["true_edges"] == 3
    assert scores["f1"] == pytest.approx(1.0) and scores["roc_auc"] == pytest.approx(1.0)
    result = compare(pixels, state)
    assert set(result["rows"]) == {"pixels (slots), last report", "state, last report", "state, final graph"}
    assert result["slots"] == {"fg_ari": 0.9}
