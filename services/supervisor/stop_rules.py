"""When a local run stops: a target score, a stable graph, an env-step budget (with the learner's
catch-up), a time budget.

A target score needs the true graph; a stable graph does not: with ``--stable-reports`` and/or
``--stable-seconds`` the run stops once that many graph reports in a row (that long) carry the same
graph and the newest has no undecided entry (every entry's confidence interval on one side of the
edge rule's boundary, :func:`causal.edge_tests.decide`). Under ``--evaluator-bias mirror`` (and
``mirror-permuted``) the boundary is a level placed inside the non-edges' tail, where some non-edge's interval always reaches
it, and the rate, not each entry's interval, bounds the errors there: so its dynamics entries left
undecided do not hold a stable graph back once the evaluator's draw is at its largest (more data
cannot come; a CBM reward entry, tested against ``min_cmi``, still does).

With ``--learner-updates-per-env-step`` the env-step budget does not stop the run at once: the
env-workers are paused (the supervisor repeats ``pause`` every second so a restarted worker pauses
too) and the run stops when a graph report comes from weights trained ``CATCH_UP_TOLERANCE`` x ratio x
budget updates, or after ``--catch-up-timeout-s``. So every collector ends with the same data and the
same training, however fast it collected.
"""
from __future__ import annotations

import logging
from typing import Callable

from proto.messages import GraphReport
from services.supervisor.config import RunConfig

log = logging.getLogger("supervisor")
CATCH_UP_TOLERANCE = 0.98


def learner_caught_up(report: GraphReport | None, ratio: float, max_env_steps: int) -> bool:
    """Whether ``report`` scores weights trained for (about) ``ratio`` x ``max_env_steps`` updates.

    The learner never exceeds its ratio of the steps it ingested, so such weights have also seen
    (about) the whole budget."""
    return report is not None and report.updates >= CATCH_UP_TOLERANCE * ratio * max_env_steps


class StableGraph:
    """Whether the graph has stopped changing: the same adjacency (and reward parents) for ``reports``
    reports in a row and ``seconds``, with no undecided entry in the newest report (0 turns a
    condition off; both 0: never)."""

    def __init__(self, reports: int, seconds: float, largest_draw: int = 0) -> None:
        self.reports, self.seconds = reports, seconds
        self.largest_draw = largest_draw
        """The evaluator's largest draw of held-out transitions (0: unknown, undecided entries always
        hold the run back)."""
        self._last: tuple[int, float] | None = None
        self._graph = b""
        self.count, self.since = 0, 0.0
        """Reports in a row with the current graph, and when it first appeared."""

    def observe(self, report: GraphReport | None, elapsed: float) -> None:
        """Count ``report`` once (the supervisor passes the newest report at every check); nothing
        to count while the rule is off."""
        if not (self.reports or self.seconds) or report is None or (report.weights_version, report.timestamp) == self._last:
            return
        self._last = (report.weights_version, report.timestamp)
        graph = report.decided_graph()
        if graph == self._graph:
            self.count += 1
        else:
            self._graph, self.count, self.since = graph, 1, elapsed

    def reason(self, report: GraphReport | None, elapsed: float) -> str:
        """Why the graph counts as settled now, or ``""``."""
        self.observe(report, elapsed)
        if not (self.reports or self.seconds) or report is None or report.undecided is None:
            return ""
        settled = self.count >= self.reports and elapsed - self.since >= self.seconds
        open_ = report.undecided_count()  # CBM: the reward's parents decided too
        if not settled or (open_ and not self.undecidable(report)):
            return ""
        stable = f"graph stable: unchanged for {self.count} reports ({elapsed - self.since:.0f}s), "
        if open_:
            return stable + (f"{open_} entries undecided at the mirror level with the largest draw "
                             f"({report.num_heldout} held-out transitions)")
        return stable + f"no undecided entry ({report.edge_rule} rule)"

    def undecidable(self, report: GraphReport) -> bool:
        """Whether the newest report's undecided entries are all dynamics entries at a mirror level
        estimated on the evaluator's largest draw (the module's docstring)."""
        reward_open = report.reward_undecided is not None and bool(report.reward_undecided.any())
        return (report.edge_rule == "fdr" and report.bias in ("mirror", "mirror-permuted") and not reward_open
                and self.largest_draw > 0 and report.num_heldout >= self.largest_draw)


class StopRules:
    """Decides, from the newest report and the env steps so far, whether and why the run stops."""

    def __init__(self, cfg: RunConfig, pause_workers: Callable[[], None]) -> None:
        self.cfg, self.pause_workers = cfg, pause_workers
        self.budget_reached_at: float | None = None
        self._last_pause = -1e9
        self.stable = StableGraph(cfg.stable_reports, cfg.stable_seconds,
                                  max(cfg.evaluator.eval_samples, cfg.evaluator.eval_samples_max))

    def check(self, elapsed: float, report: GraphReport | None, env_steps: int) -> str:
        """The reason to stop now, or ``""``."""
        cfg = self.cfg
        reason = ""
        if cfg.target_f1 and report is not None and report.metrics.get(cfg.target_metric, 0.0) >= cfg.target_f1:
            reason = f"target {cfg.target_metric} {cfg.target_f1} reached"
        elif stable := self.stable.reason(report, elapsed):
            reason = stable
        elif cfg.max_env_steps and env_steps >= cfg.max_env_steps:
            reason = (self._catch_up(elapsed, report) if cfg.learner.updates_per_env_step > 0
                      else f"env step budget {cfg.max_env_steps} reached")
        if not reason and cfg.max_seconds and elapsed >= cfg.max_seconds:
            reason = f"time budget {cfg.max_seconds:.0f}s reached"
        return reason

    def _catch_up(self, elapsed: float, report: GraphReport | None) -> str:
        """Env-step budget reached with a ratio set: keep the env-workers paused until the graph
        reflects a learner that made its share of updates (or the catch-up timeout passes)."""
        cfg = self.cfg
        if self.budget_reached_at is None:
            self.budget_reached_at = elapsed
            log.warning("env step budget %d reached: env-workers paused until the learner catches up", cfg.max_env_steps)
        if elapsed - self._last_pause >= 1.0:
            self._last_pause = elapsed
            self.pause_workers()
        if learner_caught_up(report, cfg.learner.updates_per_env_step, cfg.max_env_steps):
            return f"env step budget {cfg.max_env_steps} reached, learner caught up ({report.updates} updates)"
        if elapsed - self.budget_reached_at >= cfg.catch_up_timeout_s:
            return (f"env step budget {cfg.max_env_steps} reached, learner did not catch up "
                    f"in {cfg.catch_up_timeout_s:.0f}s")
        return ""
