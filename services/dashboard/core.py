"""dashboard core: per run, the latest graph report and local-graph report, a bounded learning curve
of each, and the services' last beats.

Pure: no bus, no HTTP. Messages arrive already validated by the shell's ``Inbox``; nothing here checks
them again. ``snapshot`` and ``runs`` produce the JSON-able documents the page renders. Every public
method takes the state's lock, so the bus loop writes while HTTP threads read.
"""
from __future__ import annotations

import threading
from dataclasses import asdict, dataclass, field
from typing import TypeVar

from proto.messages import GraphReport, LocalGraphReport, ServiceStats
from services.dashboard.cells import cause_names, classify, count_outcomes, short
from services.dashboard.coverage import run_coverage
from services.dashboard.local_graph import LocalPoint, local_graph_document
from services.dashboard.reward_graph import reward_document
from services.runtime.live_scores import live_row

CURVE_METRICS = ("f1", "accuracy", "precision", "recall", "roc_auc", "best_threshold_f1", "identifiable_f1",
                 "with_self_best_threshold_f1", "with_self_accuracy", "reward_f1", "abstraction_accuracy")
ABSTRACTION_CLASSES = (("controllable", "Controllable"), ("action_relevant", "Action-relevant"),
                       ("action_irrelevant", "Action-irrelevant"))


@dataclass(frozen=True)
class CurvePoint:
    """One report's scores on the learning curve (None where the run has no ground truth)."""

    time: float
    env_steps: int
    updates: int
    f1: float | None
    accuracy: float | None
    precision: float | None
    recall: float | None
    roc_auc: float | None
    best_threshold_f1: float | None
    identifiable_f1: float | None = None
    """F1 without the columns of constant factors (manipulation); equal to ``f1`` elsewhere."""
    with_self_best_threshold_f1: float | None = None
    """Best-threshold F1 over every entry, self-edges counted found: Table 3.1's scoring (README, Scoring)."""
    with_self_accuracy: float | None = None
    """Accuracy at the working threshold, scored the same way."""
    reward_f1: float | None = None
    """F1 of the learned reward parents against the true ones (a method with a reward graph: CBM)."""
    abstraction_accuracy: float | None = None
    """Share of factors the minimal task abstraction keeps or drops as the true one does (CBM)."""

    @classmethod
    def of(cls, report: GraphReport, time: float) -> CurvePoint:
        scores = {name: short(report.metrics[name]) if name in report.metrics else None for name in CURVE_METRICS}
        return cls(time=time, env_steps=report.env_steps, updates=report.updates, **scores)


Point = TypeVar("Point", CurvePoint, LocalPoint, dict)


@dataclass
class ServiceBeat:
    """The newest stats beat of one service instance, and when it arrived here."""

    stats: ServiceStats
    last_seen: float


@dataclass
class RunState:
    """What the dashboard knows about one run."""

    run: str
    report: GraphReport | None = None
    received_at: float = 0.0
    curve: list[CurvePoint] = field(default_factory=list)
    services: dict[tuple[str, str], ServiceBeat] = field(default_factory=dict)
    last_seen: float = 0.0
    local: LocalGraphReport | None = None
    local_received_at: float = 0.0
    local_curve: list[LocalPoint] = field(default_factory=list)
    live_curve: list[dict[str, float]] = field(default_factory=list)
    """The dynamics-learner's live scores (FLAM's PSNR, DCI, per-slot KL) each time they change."""

    @property
    def updated_at(self) -> float:
        """When the newest report of either kind arrived (0 before any)."""
        return max(self.received_at, self.local_received_at)


class DashboardState:
    """The latest graph and local graphs, their learning curves and the service beats of up to
    ``max_runs`` runs; a snapshot shows at most ``local_examples`` example transitions."""

    def __init__(self, history_points: int = 1_000, max_runs: int = 64, max_services: int = 256,
                 stale_after_s: float = 10.0, local_examples: int = 8) -> None:
        if history_points < 2 or max_runs < 1 or max_services < 1 or local_examples < 1:
            raise ValueError("history_points >= 2, max_runs, max_services and local_examples >= 1 are required")
        self.history_points, self.max_runs, self.max_services = history_points, max_runs, max_services
        self.stale_after_s, self.local_examples = stale_after_s, local_examples
        self._runs: dict[str, RunState] = {}
        self._lock = threading.RLock()

    def add_report(self, run: str, report: GraphReport, now: float) -> bool:
        """Keep ``report`` if it is newer than the run's latest; False for a duplicate or a stale one."""
        with self._lock:
            state = self._run(run, now)
            if state.report is not None and _order(report) <= _order(state.report):
                return False
            state.report, state.received_at = report, now
            state.curve = self._extended(state.curve, CurvePoint.of(report, report.timestamp or now))
            return True

    def add_local_report(self, run: str, report: LocalGraphReport, now: float) -> bool:
        """Keep a local-graph report as ``add_report`` keeps a graph report."""
        with self._lock:
            state = self._run(run, now)
            if state.local is not None and _order(report) <= _order(state.local):
                return False
            state.local, state.local_received_at = report, now
            state.local_curve = self._extended(state.local_curve, LocalPoint.of(report, report.timestamp or now))
            return True

    def _extended(self, curve: list[Point], point: Point) -> list[Point]:
        """``curve`` + ``point``, thinned evenly first when full, so it still spans the whole run."""
        return (curve[::2] if len(curve) >= self.history_points else curve) + [point]

    def add_stats(self, run: str, stats: ServiceStats, now: float) -> None:
        """Remember the newest beat of one service instance; a dynamics-learner's new live scores
        extend the run's live curve (``time`` is the beat's timestamp)."""
        with self._lock:
            state = self._run(run, now)
            services = state.services
            key = (stats.service, stats.instance)
            if key not in services and len(services) >= self.max_services:
                del services[min(services, key=lambda k: services[k].last_seen)]
            services[key] = ServiceBeat(stats, now)
            if stats.service == "dynamics-learner":
                row = live_row(stats.values, state.live_curve[-1] if state.live_curve else None, stats.timestamp)
                if row is not None:
                    state.live_curve = self._extended(state.live_curve, row)

    def run_ids(self) -> list[str]:
        with self._lock:
            return list(self._runs)

    def runs(self, now: float) -> list[dict]:
        """The run list: runs with a graph or local graphs first, most recently updated first."""
        with self._lock:
            states = sorted(self._runs.values(), key=lambda s: (s.updated_at > 0, s.updated_at, s.last_seen),
                            reverse=True)
            return [_run_summary(s, now) for s in states]

    def snapshot(self, run: str, now: float) -> dict | None:
        """Everything the page shows for ``run``; None for an unknown run."""
        with self._lock:
            state = self._runs.get(run)
            if state is None:
                return None
            graph = graph_document(state.report, state.received_at) if state.report is not None else None
            services = self._services(state, now)
            return {"run": run, "server_time": now, "graph": graph, "history": [asdict(p) for p in state.curve],
                    "local_graph": self._local_document(state), "services": services,
                    "induced_coverage": run_coverage(services), "live_history": list(state.live_curve)}

    def _local_document(self, state: RunState) -> dict | None:
        if state.local is None:
            return None
        return local_graph_document(state.local, state.local_received_at, state.local_curve, self.local_examples)

    def services(self, run: str, now: float) -> list[dict] | None:
        """The service beats of ``run``, or None for an unknown run."""
        with self._lock:
            state = self._runs.get(run)
            return None if state is None else self._services(state, now)

    def live_history(self, run: str) -> list[dict[str, float]]:
        """The run's live-score curve (empty for an unknown run or one without live scores)."""
        with self._lock:
            state = self._runs.get(run)
            return [] if state is None else list(state.live_curve)

    def _services(self, state: RunState, now: float) -> list[dict]:
        return [{"service": s, "instance": i, "values": beat.stats.values, "timestamp": beat.stats.timestamp,
                 "last_seen": beat.last_seen, "age_s": max(now - beat.last_seen, 0.0),
                 "stale": now - beat.last_seen > self.stale_after_s}
                for (s, i), beat in sorted(state.services.items())]

    def _run(self, run: str, now: float) -> RunState:
        state = self._runs.get(run)
        if state is None:
            if len(self._runs) >= self.max_runs:
                del self._runs[min(self._runs, key=lambda r: self._runs[r].last_seen)]
            state = self._runs[run] = RunState(run)
        state.last_seen = now
        return state


def _order(report: GraphReport | LocalGraphReport) -> tuple[float, int]:
    return report.timestamp, report.weights_version


def _run_summary(state: RunState, now: float) -> dict:
    report, local = state.report, state.local
    return {"run": state.run, "has_graph": report is not None,
            "kind": report.kind if report else local.kind if local else None,
            "weights_version": report.weights_version if report else None,
            "env_steps": report.env_steps if report else None,
            "f1": report.metrics.get("f1") if report else None,
            "has_local": local is not None,
            "local_weights_version": local.weights_version if local else None,
            "local_roc_auc": local.metrics.get("roc_auc") if local else None,
            "updated_at": state.updated_at or None, "last_seen": state.last_seen,
            "services": len(state.services)}


def graph_document(report: GraphReport, received_at: float) -> dict:
    """A report as the page draws it: cells (CMI, learned, true, TP/FP/FN/TN), classes, scores."""
    names = list(report.factor_names)
    outcome = classify(report.adjacency, report.true_graph)
    truth = report.true_graph
    stderr, undecided, null = report.cmi_stderr, report.undecided, report.cmi_null
    cells = [[{"cmi": short(report.cmi[i, j]), "learned": bool(report.adjacency[i, j]),
               "truth": None if truth is None else bool(truth[i, j]), "outcome": outcome[i][j],
               **({} if stderr is None else {"stderr": short(stderr[i, j]), "undecided": bool(undecided[i, j])}),
               **({} if null is None else {"null": short(null[i, j])})}
              for j in range(report.cmi.shape[1])] for i in range(report.cmi.shape[0])]
    counts = None if truth is None else count_outcomes(outcome)
    classes = [{"key": key, "label": label, "factors": [{"index": i, "name": names[i]} for i in getattr(report, key)]}
               for key, label in ABSTRACTION_CLASSES]
    reward = reward_document(report)
    return {"kind": report.kind, "weights_version": report.weights_version, "env_steps": report.env_steps,
            "updates": report.updates, "num_heldout": report.num_heldout, "timestamp": report.timestamp,
            "received_at": received_at, "threshold": report.threshold, "factor_names": names,
            "cause_names": cause_names(names), "metrics": dict(report.metrics),
            "cmi_max": short(report.cmi.max()), "confusion": counts, "cells": cells,
            "classes": classes if reward is None else reward["classes"], "reward": reward,
            "abstraction": "cdl" if reward is None else "minimal", **edge_rule_document(report)}


def edge_rule_document(report: GraphReport) -> dict:
    """How the report's edges were decided (``bias``: what the fdr rule tests the dynamics CMI against),
    and how many entries are undecided (None without standard errors)."""
    return {"edge_rule": report.edge_rule, "fdr": report.fdr, "min_cmi": report.min_cmi, "bias": report.bias,
            "reward_min_cmi": report.reward_min_cmi,
            "undecided": None if report.undecided is None else int(report.undecided.sum())}

