"""``causeway status``: every service of a run, from its liveliness token and its latest stats beats.

    causeway status (--run RUN [--connect ENDPOINT] | --run-dir runs/X) [--listen-s 2.5] [--json]

Listens ``--listen-s`` seconds (two beats at the services' 1 s interval), then prints one row per
instance: its state, a rate from the first and last beat of the window (env steps/s of an
env-worker, updates/s of the learner, reports/min of the evaluator), a few key values and how long
ago it last beat. States: ``alive`` (token held), ``gone`` (token lost during the window, or beats
without a token), ``restarted`` (token lost and back during the window). An alive instance that has
not beaten yet shows "no stats yet". Exit 0 when the router answered, 2 when it could not be reached.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from typing import Sequence, TextIO

from proto.messages import ServiceStats
from services.ops.observe import Instance, Observation, observe
from services.ops.target import Target, add_target_arguments, open_bus, resolve_target


@dataclass(frozen=True)
class RateSpec:
    """Which counter of a service's beat its rate is taken from, and how it is shown."""

    key: str
    unit: str
    per_seconds: float = 1.0


RATES: dict[str, RateSpec] = {
    "env-worker": RateSpec("env_steps", "steps/s"),
    "dynamics-learner": RateSpec("updates", "updates/s"),
    "graph-evaluator": RateSpec("reports", "reports/min", 60.0),
}
KEY_VALUES: dict[str, tuple[str, ...]] = {
    "env-worker": ("env_steps", "episodes"),
    "dynamics-learner": ("updates", "env_steps", "replay_size", "weights_version", "nll_full"),
    "graph-evaluator": ("evaluated_version", "reports", "heldout", "f1", "best_threshold_f1"),
}
NO_STATS = "no stats yet"


@dataclass(frozen=True)
class InstanceStatus:
    """One row of the status table."""

    service: str
    instance: str
    state: str
    """alive, gone or restarted (see the module docstring)."""
    token: bool
    """Whether the instance's liveliness token was alive at the end of the window."""
    rate: float | None
    rate_unit: str
    values: dict[str, float]
    """The newest beat's values (empty when no beat arrived)."""
    last_seen_s: float | None
    """Seconds between the newest beat and the end of the window."""
    beats: int


def instance_state(observation: Observation, instance: Instance) -> str:
    """alive, gone or restarted, from the token now and its changes during the window."""
    lost = any(not c.alive for c in observation.changes_of(instance))
    if instance not in observation.alive:
        return "gone"
    return "restarted" if lost else "alive"


def rate(beats: Sequence[ServiceStats], spec: RateSpec) -> float | None:
    """Rate of ``spec.key`` over the beats since the counter last went down (a restart resets it)."""
    points = [(b.timestamp, b.values[spec.key]) for b in beats if spec.key in b.values]
    for i in range(len(points) - 1, 0, -1):
        if points[i][1] < points[i - 1][1]:
            points = points[i:]
            break
    if len(points) < 2 or points[-1][0] <= points[0][0]:
        return None
    return (points[-1][1] - points[0][1]) / (points[-1][0] - points[0][0]) * spec.per_seconds


def instance_status(observation: Observation, instance: Instance) -> InstanceStatus:
    service, name = instance
    beats = observation.beats.get(instance, ())
    spec = RATES.get(service)
    newest = beats[-1] if beats else None
    return InstanceStatus(
        service=service, instance=name, state=instance_state(observation, instance),
        token=instance in observation.alive, rate=rate(beats, spec) if spec else None,
        rate_unit=spec.unit if spec else "", values=dict(newest.values) if newest else {},
        last_seen_s=round(max(observation.ended - newest.timestamp, 0.0), 2) if newest else None,
        beats=len(beats))


def statuses(observation: Observation) -> list[InstanceStatus]:
    return [instance_status(observation, i) for i in observation.instances()]


def totals(rows: Sequence[InstanceStatus]) -> dict[str, dict[str, float | int | str]]:
    """Per service: instances alive, and the sum of their rates (where any has one)."""
    out: dict[str, dict[str, float | int | str]] = {}
    for row in rows:
        entry = out.setdefault(row.service, {"alive": 0, "rate": 0.0, "rate_unit": row.rate_unit})
        entry["alive"] = int(entry["alive"]) + int(row.token)
        if row.token and row.rate is not None:
            entry["rate"] = float(entry["rate"]) + row.rate
    return out


def _number(value: float) -> str:
    if value == int(value) and abs(value) < 1e15:
        return f"{int(value):,}"
    return f"{value:.4g}" if abs(value) < 1000 else f"{value:,.0f}"


def _rate(value: float, unit: str) -> str:
    return f"{value:,.0f} {unit}" if abs(value) >= 100 else f"{value:.1f} {unit}"


def _rate_cell(row: InstanceStatus) -> str:
    if not row.beats:
        return NO_STATS if row.token else "-"
    return "-" if row.rate is None else _rate(row.rate, row.rate_unit)


def _values_cell(row: InstanceStatus) -> str:
    keys = KEY_VALUES.get(row.service, tuple(sorted(row.values))[:5])
    shown = [f"{k}={_number(row.values[k])}" for k in keys if k in row.values]
    if row.values.get("messages_rejected"):
        shown.append(f"rejected={_number(row.values['messages_rejected'])}")
    return " ".join(shown)


def render_table(rows: Sequence[InstanceStatus]) -> str:
    """An aligned text table, one line per instance."""
    header = ("SERVICE", "INSTANCE", "STATE", "RATE", "LAST BEAT", "VALUES")
    cells = [header] + [(r.service, r.instance, r.state, _rate_cell(r),
                         "-" if r.last_seen_s is None else f"{r.last_seen_s:.1f}s ago", _values_cell(r))
                        for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(header) - 1)]
    return "\n".join("  ".join(c[i].ljust(w) for i, w in enumerate(widths)) + "  " + c[-1] for c in cells)


def render_totals(summary: dict[str, dict[str, float | int | str]]) -> str:
    parts = [f"{svc} x{entry['alive']}" + (" " + _rate(float(entry["rate"]), str(entry["rate_unit"])) if entry["rate"] else "")
             for svc, entry in sorted(summary.items())]
    return "alive: " + ", ".join(parts)


def report(target: Target, observation: Observation) -> dict:
    """The ``--json`` document."""
    rows = statuses(observation)
    return {"run": target.run_id, "router": target.connect,
            "listened_s": round(observation.ended - observation.started, 2),
            "services": [asdict(r) for r in rows], "totals": totals(rows),
            "stats_rejected": observation.rejected}


def render(target: Target, observation: Observation) -> str:
    """The table and a totals line, or one line saying that nobody is there."""
    rows = statuses(observation)
    if not rows:
        return (f"run {target.run_id} on {target.connect}: no live services "
                f"(listened {observation.ended - observation.started:.1f}s)")
    return render_table(rows) + "\n" + render_totals(totals(rows))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="causeway status", description="Live services of a run, with their rates.")
    add_target_arguments(p)
    p.add_argument("--listen-s", type=float, default=2.5, help="seconds to collect stats beats (default 2.5)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    return p


def main(argv: Sequence[str], out: TextIO | None = None) -> int:
    args = parser().parse_args(list(argv))
    target = resolve_target(args)
    with open_bus(target) as bus:
        observation = observe(bus, target.run_id, args.listen_s)
    text = json.dumps(report(target, observation), indent=1) if args.json else render(target, observation)
    (out or sys.stdout).write(text + "\n")
    return 0
