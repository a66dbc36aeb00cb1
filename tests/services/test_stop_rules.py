"""The stop rule without ground truth (issue 22): the graph unchanged for a number of reports and a time,
and no entry undecided in the newest report; checked on hand-made reports."""
from __future__ import annotations

import dataclasses

import numpy as np

from proto.messages import GraphReport
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.stop_rules import StableGraph, StopRules


def report(version: int, edges: tuple[tuple[int, int], ...] = ((1, 0),), undecided: int = 0,
           with_errors: bool = True) -> GraphReport:
    """A two-factor report with ``edges`` (self-edges always) and ``undecided`` undecided entries."""
    adjacency = np.eye(2, 3, dtype=np.uint8)
    for cell in edges:
        adjacency[cell] = 1
    open_cells = np.zeros((2, 3), np.uint8)
    open_cells.flat[[1, 2, 3, 5][:undecided]] = 1
    tested = ({"cmi_stderr": np.full((2, 3), 1e-3, np.float32), "undecided": open_cells} if with_errors else {})
    return GraphReport(kind="cdl", weights_version=version, env_steps=100 * version, updates=10 * version,
                       factor_names=("a", "b"), cmi=np.zeros((2, 3), np.float32), adjacency=adjacency,
                       threshold=0.02, controllable=(), action_relevant=(), action_irrelevant=(0, 1),
                       timestamp=float(version), **tested)


def test_stops_after_the_same_graph_for_enough_reports_and_nothing_undecided() -> None:
    rule = StableGraph(reports=3, seconds=0.0)
    assert rule.reason(report(1), 1.0) == "" and rule.reason(report(2), 2.0) == ""
    assert rule.reason(report(2), 2.5) == ""  # the same report seen again is not counted again
    assert "unchanged for 3 reports" in rule.reason(report(3), 3.0)


def test_a_changed_graph_starts_the_count_over() -> None:
    rule = StableGraph(reports=3, seconds=0.0)
    for version in (1, 2):
        rule.reason(report(version), float(version))
    assert rule.reason(report(3, edges=((1, 0), (0, 2))), 3.0) == "" and rule.count == 1
    assert rule.reason(report(4, edges=((1, 0), (0, 2))), 4.0) == ""
    assert rule.reason(report(5, edges=((1, 0), (0, 2))), 5.0) != ""


def test_undecided_entries_keep_the_run_going() -> None:
    rule = StableGraph(reports=2, seconds=0.0)
    assert rule.reason(report(1, undecided=1), 1.0) == ""
    assert rule.reason(report(2, undecided=1), 2.0) == ""  # stable, but one entry undecided
    assert rule.reason(report(3), 3.0) != ""  # still the same graph, now decided


def test_an_undecided_reward_parent_keeps_the_run_going() -> None:
    """CBM: its reward graph has standard errors too; a stable graph with a reward entry undecided is
    not settled, and a changed reward parent starts the count over."""
    def with_reward(version: int, parents: tuple[int, ...], undecided: tuple[int, ...] = ()) -> GraphReport:
        base = report(version)
        open_cells = np.zeros(3, np.uint8)
        open_cells[list(undecided)] = 1
        return dataclasses.replace(base, reward_parents=np.array([int(i in parents) for i in range(3)], np.uint8),
                                   reward_undecided=open_cells)

    rule = StableGraph(reports=2, seconds=0.0)
    assert rule.reason(with_reward(1, (0,), undecided=(1,)), 1.0) == ""
    assert rule.reason(with_reward(2, (0,), undecided=(1,)), 2.0) == ""  # stable, a reward entry open
    assert rule.reason(with_reward(3, (0, 1)), 3.0) == "" and rule.count == 1  # a new parent: count over
    assert rule.reason(with_reward(4, (0, 1)), 4.0) != ""


def test_under_mirror_entries_undecided_at_the_level_stop_only_with_the_largest_draw() -> None:
    """``--evaluator-bias mirror``: the level sits in the non-edges' tail, so a stable graph whose only
    undecided entries are the dynamics graph's stops once the draw is at its largest, and not before;
    under any other bias, or with a reward entry open, undecided entries keep the run going."""
    def tested(version: int, bias: str = "mirror", draw: int = 16_000, undecided: int = 2) -> GraphReport:
        return dataclasses.replace(report(version, undecided=undecided), edge_rule="fdr", bias=bias,
                                   min_cmi=3.5e-4, num_heldout=draw)

    rule = StableGraph(reports=2, seconds=0.0, largest_draw=16_000)
    assert rule.reason(tested(1, draw=8_000), 1.0) == "" and rule.reason(tested(2, draw=8_000), 2.0) == ""
    reason = rule.reason(tested(3), 3.0)
    assert "2 entries undecided at the mirror level with the largest draw (16000" in reason
    permuted = StableGraph(reports=2, seconds=0.0, largest_draw=16_000)   # the same under mirror-permuted
    assert permuted.reason(tested(1, bias="mirror-permuted"), 1.0) == ""
    assert "undecided at the mirror level" in permuted.reason(tested(2, bias="mirror-permuted"), 2.0)
    for other in ("fixed", "split"):
        held = StableGraph(reports=2, seconds=0.0, largest_draw=16_000)
        assert all(held.reason(tested(v, bias=other), float(v)) == "" for v in (1, 2, 3))
    reward_open = dataclasses.replace(tested(4), reward_parents=np.zeros(3, np.uint8),
                                      reward_undecided=np.array([0, 1, 0], np.uint8))
    assert StableGraph(reports=1, seconds=0.0, largest_draw=16_000).reason(reward_open, 4.0) == ""
    unknown = StableGraph(reports=1, seconds=0.0)
    assert unknown.reason(tested(5), 5.0) == ""
    assert StopRules(build_config(RunConfig, stable_reports=1), lambda: None).stable.largest_draw == 16_000


def test_time_and_reports_must_both_hold() -> None:
    rule = StableGraph(reports=2, seconds=60.0)
    assert rule.reason(report(1), 0.0) == "" and rule.reason(report(2), 30.0) == ""  # 2 reports, 30 s
    assert rule.reason(report(2), 59.0) == ""
    assert "60s" in rule.reason(report(2), 60.0)
    only_time = StableGraph(reports=0, seconds=10.0)
    assert only_time.reason(report(1), 0.0) == "" and only_time.reason(report(1), 10.0) != ""


def test_off_by_default_and_without_standard_errors() -> None:
    off = StableGraph(reports=0, seconds=0.0)
    assert all(off.reason(report(v), float(v)) == "" for v in range(1, 5))
    blind = StableGraph(reports=1, seconds=0.0)
    assert blind.reason(report(1, with_errors=False), 1.0) == ""  # cannot tell what is undecided


def test_stop_rules_report_the_stable_graph_before_the_budgets() -> None:
    rules = StopRules(build_config(RunConfig, stable_reports=2, max_seconds=100.0), lambda: None)
    assert rules.check(1.0, report(1), 0) == ""
    assert rules.check(2.0, report(2), 0).startswith("graph stable")
    assert rules.check(200.0, None, 0).startswith("time budget")
