"""The live progress line of ``causeway run``: what each service last reported."""
from __future__ import annotations

import sys
import time
from typing import TextIO

from proto.messages import GraphReport, LocalGraphReport, ServiceStats


CUMULATIVE = ("env_steps", "episodes", "updates")
RESUMED = {"updates": "resumed_at_update"}
"""Counters a restarted process resumes from its checkpoint (the learner's updates): already totals
of the model's updates, so a fall is work lost since the checkpoint, not a count restarting at 0."""


class Progress:
    """Keeps the newest stats per service instance and renders one status line."""

    def __init__(self, stream: TextIO = sys.stderr, interactive: bool | None = None, every_s: float = 10.0,
                 global_graph: bool = True, local_graphs: bool = False) -> None:
        """``global_graph`` / ``local_graphs``: which reports the run's method and env give (the line
        says it waits for one only where one will come)."""
        self.global_graph, self.local_graphs = global_graph, local_graphs
        self.stream = stream
        self.interactive = stream.isatty() if interactive is None else interactive
        self.every_s = every_s
        self.stats: dict[tuple[str, str], ServiceStats] = {}
        self.carried: dict[tuple[str, str, str], float] = {}
        self.report: GraphReport | None = None
        self.local: LocalGraphReport | None = None
        self.started = time.monotonic()
        self._last_line = 0.0
        self._rate: dict[str, tuple[float, float]] = {}

    def on_stats(self, stats: ServiceStats) -> None:
        """Keep the newest beat per instance; a counter that falls (a restarted process counting
        from zero again) carries its previous total, so run totals never go backwards. A counter
        the process resumes from its checkpoint (:data:`RESUMED`) is taken as it is."""
        ident = (stats.service, stats.instance)
        previous = self.stats.get(ident)
        if previous is not None:
            for key in CUMULATIVE:
                if RESUMED.get(key, "") in stats.values:
                    continue
                if stats.values.get(key, 0.0) < previous.values.get(key, 0.0):
                    self.carried[ident + (key,)] = self.carried.get(ident + (key,), 0.0) + previous.values[key]
        self.stats[ident] = stats

    def on_report(self, report: GraphReport) -> None:
        self.report = report

    def on_local_report(self, report: LocalGraphReport) -> None:
        self.local = report

    def value(self, service: str, key: str) -> float:
        return sum(s.values.get(key, 0.0) + self.carried.get((svc, inst, key), 0.0)
                   for (svc, inst), s in self.stats.items() if svc == service)

    def mean(self, service: str, key: str) -> float | None:
        """The mean of ``key`` over the instances of ``service`` that report it (None if none does)."""
        values = [s.values[key] for (svc, _), s in self.stats.items() if svc == service and key in s.values]
        return sum(values) / len(values) if values else None

    def env_steps(self) -> int:
        return int(self.value("env-worker", "env_steps"))

    def updates(self) -> int:
        return int(self.value("dynamics-learner", "updates"))

    def transitions_lost(self) -> dict[str, int]:
        """What the dynamics-learner counted lost on the way to it (``seq`` gaps), from its newest beat:
        its count is resumed from its checkpoint, so it is the run's."""
        learner = self.stats.get(("dynamics-learner", "0"))
        values = learner.values if learner is not None else {}
        return {"batches": int(values.get("lost_batches", 0)), "steps": int(values.get("lost_steps", 0))}

    def _per_second(self, name: str, total: float) -> float:
        now = time.monotonic()
        last_t, last_v = self._rate.get(name, (now, total))
        self._rate[name] = (now, total)
        return (total - last_v) / (now - last_t) if now > last_t else 0.0

    def live_scores(self, most: int = 4) -> dict[str, float]:
        """The learner's newest live scores (``live_*`` in its beat: FLAM's PSNR and DCI), per-slot
        ones left out, at most ``most``."""
        learner = self.stats.get(("dynamics-learner", "0"))
        values = learner.values if learner is not None else {}
        live = {k.removeprefix("live_"): v for k, v in values.items()
                if k.startswith("live_") and not k.startswith("live_slot")}
        return dict(list(live.items())[:most])

    def line(self, restarts: int) -> str:
        elapsed = time.monotonic() - self.started
        steps, updates = self.env_steps(), self.updates()
        training = f"updates {updates:,} ({self._per_second('upd', updates):.1f}/s)"
        if (nll := self.mean("dynamics-learner", "nll_full")) is not None:
            training += f" nll {nll:.3f}"  # NLL per factor (CDL, CBM, ELDEN); FLAM and Dyn-O have none
        parts = [f"[{elapsed:6.0f}s]", f"env {steps:,} steps ({self._per_second('env', steps):,.0f}/s)", training]
        if self.report is not None and self.report.metrics:
            m = self.report.metrics
            parts.append(f"graph v{self.report.weights_version} F1 {m['f1']:.3f} acc {m['accuracy']:.3f} "
                         f"(best-threshold F1 {m['best_threshold_f1']:.3f})")
        elif self.report is not None:
            parts.append(f"graph v{self.report.weights_version} ({int(self.report.adjacency.sum())} edges)")
        elif self.global_graph:
            parts.append("graph: waiting for the first report")
        if self.local is not None:
            m = self.local.metrics
            parts.append(f"local graphs v{self.local.weights_version} ROC AUC {m['roc_auc']:.3f} "
                         f"best F1 {m['best_f1']:.3f}")
        elif self.local_graphs and not self.global_graph:
            parts.append("local graphs: waiting for the first report")
        if live := self.live_scores():
            parts.append("live " + " ".join(f"{k} {v:.3g}" for k, v in live.items()))
        if restarts:
            parts.append(f"restarts {restarts}")
        return " | ".join(parts)

    def show(self, restarts: int, force: bool = False) -> None:
        now = time.monotonic()
        if self.interactive:
            if force or now - self._last_line >= 0.5:
                self.stream.write("\r\x1b[2K" + self.line(restarts))
                self.stream.flush()
                self._last_line = now
        elif force or now - self._last_line >= self.every_s:
            self.stream.write(self.line(restarts) + "\n")
            self.stream.flush()
            self._last_line = now

    def finish(self) -> None:
        if self.interactive:
            self.stream.write("\n")
            self.stream.flush()
