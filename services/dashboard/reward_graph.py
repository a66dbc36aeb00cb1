"""dashboard: how a report's reward graph (CBM, chapter 4) reaches the page.

The reward is one more effect: a row under the dynamics graph's heat maps, with one cell per factor at
t and the action (its scores, its own threshold, and TP/FP/FN/TN against the true reward parents; with
standard errors, each cell's and whether the held-out data leave it undecided, issue 22). The
abstraction card then shows the minimal task abstraction as Fig. 4.2 (b) colours it: the reward's
parents, their ancestors in the dynamics graph, and the factors it ignores.
"""
from __future__ import annotations

from proto.messages import GraphReport
from services.dashboard.cells import OUTCOMES, short

REWARD_ROW = "reward"
MINIMAL_CLASSES = (("reward_parents", "Reward's parents"), ("reward_ancestors", "Their ancestors (dynamics)"),
                   ("dropped", "Ignored"))


def _outcome(learned: bool, truth: bool | None) -> str | None:
    if truth is None:
        return None
    return ("tp" if truth else "fp") if learned else ("fn" if truth else "tn")


def reward_document(report: GraphReport) -> dict | None:
    """The reward row (``cells``: score, learned, truth, outcome, the row's threshold, and with standard
    errors ``stderr`` and ``undecided``), its outcome counts, how many entries are undecided (None without
    standard errors) and the minimal abstraction's classes; None for a report without a reward graph."""
    if report.reward_scores is None:
        return None
    truth = report.true_reward_parents
    stderr, undecided = report.reward_stderr, report.reward_undecided
    cells = [{"cmi": short(score), "learned": bool(learned), "truth": None if truth is None else bool(truth[i]),
              "outcome": _outcome(bool(learned), None if truth is None else bool(truth[i])),
              "threshold": report.reward_threshold,
              **({} if stderr is None else {"stderr": short(stderr[i]), "undecided": bool(undecided[i])})}
             for i, (score, learned) in enumerate(zip(report.reward_scores, report.reward_parents))]
    counts = None if truth is None else {o: sum(c["outcome"] == o for c in cells) for o in OUTCOMES}
    return {"row_name": REWARD_ROW, "threshold": report.reward_threshold, "cells": cells, "confusion": counts,
            "undecided": None if undecided is None else int(undecided.sum()), "classes": minimal_classes(report)}


def minimal_classes(report: GraphReport) -> list[dict]:
    """The kept factors split into the reward's parents and their ancestors, then the ignored ones."""
    names = report.factor_names
    kept = set(report.controllable + report.action_relevant)
    parents = {j for j in kept if report.reward_parents[j]}
    members = {"reward_parents": sorted(parents), "reward_ancestors": sorted(kept - parents),
               "dropped": [j for j in range(len(names)) if j not in kept]}
    return [{"key": key, "label": label, "factors": [{"index": i, "name": names[i]} for i in members[key]]}
            for key, label in MINIMAL_CLASSES]
