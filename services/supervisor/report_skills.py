"""SkiLD's block of summary.json (ch. 6): the phases' budgets and the induced-graph coverage.

From the policy-learner's last beat: ``skild.pretrain_steps`` / ``task_steps`` (env steps of each
phase taken in), ``targets`` (target graphs the history held when the skills were frozen),
``phase`` (where the run stopped), and ``induced_coverage``: per phase, the finished episodes and the
share of them that induced each multi-object dependency at least once
(:func:`services.dashboard.coverage.induced_coverage`). The contract's ``task`` block (success
rate, return, stages) comes from the env-workers, whose episode window restarts at the phase switch.
"""
from __future__ import annotations

from typing import Any

from proto.messages import ServiceStats
from services.dashboard.coverage import induced_coverage


def skill_facts(stats: ServiceStats | None) -> dict[str, Any]:
    """``{"skild": {...}, "induced_coverage": {...}}`` from a SkiLD policy-learner's beat ({} otherwise)."""
    if stats is None:
        return {}
    coverage = induced_coverage(stats.values)
    if coverage is None:
        return {}
    v = stats.values
    return {"skild": {"phase": "task" if v.get("phase_task") else "pretrain",
                      **{k: int(v.get(k, 0)) for k in ("pretrain_steps", "task_steps", "targets", "updates",
                                                       "selector_updates", "task_updates", "policy_version")}},
            "induced_coverage": coverage}
