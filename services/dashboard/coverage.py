"""SkiLD's induced-graph coverage (ch. 6, Fig. 6.4's measure) as the page and the summary show it.

The policy-learner of a SkiLD run beats ``coverage_episodes_<phase>`` (finished episodes) and
``coverage_<phase>: <row>`` (the share of them that induced the dependency ``<row>``, e.g.
``"table, printer -> printer"``, at least once); this turns one beat's values into
``{phase: {"episodes": n, "rows": {row: share}}}``. Pure.
"""
from __future__ import annotations

PHASES = ("pretrain", "task")


def induced_coverage(values: dict[str, float]) -> dict[str, dict] | None:
    """The coverage blocks of a beat's values, or None for a beat without them."""
    out: dict[str, dict] = {}
    for phase in PHASES:
        episodes = values.get(f"coverage_episodes_{phase}")
        if episodes is None:
            continue
        prefix = f"coverage_{phase}: "
        rows = {key[len(prefix):]: float(v) for key, v in values.items() if key.startswith(prefix)}
        out[phase] = {"episodes": int(episodes), "rows": dict(sorted(rows.items(), key=lambda kv: -kv[1]))}
    return out or None


def run_coverage(services: list[dict]) -> dict[str, dict] | None:
    """The coverage of a run's service list (the policy-learner's beat), None without one."""
    for s in services:
        if s["service"] == "policy-learner":
            found = induced_coverage(s["values"])
            if found is not None:
                return found
    return None
