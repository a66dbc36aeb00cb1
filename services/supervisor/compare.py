"""``causeway compare RUN...``: finished runs side by side, by the results contract's keys.

Every method's ``summary.json`` carries its results under the same blocks (docs/scoring.md, "The results
contract"): ``final_graph`` and ``graph`` (``accuracy``, ``f1``, ``best_threshold_f1``, ``roc_auc``),
``local_graph`` (``roc_auc``, ``pr_auc``, ``best_f1``), ``task`` (``success_rate``, ``return_mean``,
``stages_mean``), ``slots`` (``fg_ari``) and ``latent_actions`` (``dci_d``, ``dci_c``, ``dci_i``,
``psnr``), each where the method produces it. This command reads those scores from any number of runs
and prints them as one markdown table, a row per run and a column per score some run has:

    causeway compare runs/a runs/b runs/c
    causeway compare runs/cdl-s0 runs/cdl-s1 runs/cdl-s2 runs/elden-s0 --mean --plot compare.png

``--mean`` folds runs of one configuration (the same method, environment and environment options;
seeds differ) into one row of mean ± sample standard deviation, the form of the chapter's tables.
``--plot`` draws one panel per score (bars, with the standard deviation as error bars under ``--mean``)
and ``--json`` writes the rows. Every path is read before anything is printed: a run without a readable
``summary.json`` is refused with its path (exit 2), and nothing is written.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

CONTRACT: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("final_graph", ("accuracy", "f1", "best_threshold_f1", "roc_auc")),
    ("graph", ("accuracy", "f1", "best_threshold_f1", "roc_auc")),
    ("local_graph", ("roc_auc", "pr_auc", "best_f1")),
    ("task", ("success_rate", "return_mean", "stages_mean")),
    ("slots", ("fg_ari",)),
    ("latent_actions", ("dci_d", "dci_c", "dci_i", "psnr")),
)
"""The results contract: (block of ``summary.json``, its scores), in the order columns are printed."""

ERROR = "error"
"""A cell whose block is present but says its scoring failed (``{"error": ...}``, e.g. ``slots``)."""


@dataclass(frozen=True)
class RunScores:
    """One finished run's contract scores (``"block.key" -> value``, or :data:`ERROR`)."""

    path: Path
    run_id: str
    method: str
    env: str
    seed: int | None
    setting: str
    """The environment's options as ``k=v`` pairs (what, besides method and env, makes a configuration)."""
    scores: dict[str, float | str] = field(default_factory=dict)


@dataclass(frozen=True)
class GroupScores:
    """Runs of one configuration: per score, the mean, the sample standard deviation and how many runs had it."""

    method: str
    env: str
    setting: str
    runs: tuple[RunScores, ...]
    mean: dict[str, float]
    sd: dict[str, float]
    count: dict[str, int]


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def contract_scores(summary: dict[str, Any]) -> dict[str, float | str]:
    """The contract's scores present in one ``summary.json`` content (absent blocks and keys left out)."""
    out: dict[str, float | str] = {}
    for block, keys in CONTRACT:
        content = summary.get(block)
        if not isinstance(content, dict):
            continue
        for key in keys:
            value = _number(content.get(key))
            if value is not None:
                out[f"{block}.{key}"] = value
            elif "error" in content:
                out[f"{block}.{key}"] = ERROR
    return out


def summary_path(path: Path) -> Path:
    return path / "summary.json" if path.is_dir() else path


def load_run(path: Path) -> RunScores:
    """A run directory's (or a ``summary.json``'s) scores; ``ValueError`` saying what is wrong with it."""
    file = summary_path(path)
    try:
        summary = json.loads(file.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no summary.json (not a finished run)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{file}: not a readable summary ({exc})") from None
    if not isinstance(summary, dict) or not isinstance(summary.get("method"), str) \
            or not isinstance(summary.get("env"), str):
        raise ValueError(f"{file}: not a run summary (no method and env)")
    options = summary.get("env_options")
    options = options if isinstance(options, dict) else {}
    setting = " ".join(f"{k}={options[k]}" for k in sorted(options) if options[k] not in (None, ""))
    seed = summary.get("seed")
    return RunScores(path=path, run_id=str(summary.get("run_id") or path.name), method=summary["method"],
                     env=summary["env"], seed=seed if isinstance(seed, int) and not isinstance(seed, bool) else None,
                     setting=setting, scores=contract_scores(summary))


def columns(runs: Sequence[RunScores]) -> list[str]:
    """The contract's scores any of ``runs`` has, in contract order."""
    present = {key for run in runs for key in run.scores}
    return [f"{block}.{key}" for block, keys in CONTRACT for key in keys if f"{block}.{key}" in present]


def group(runs: Sequence[RunScores]) -> list[GroupScores]:
    """Runs folded by configuration (method, env, env options), in the order each first appears."""
    by_config: dict[tuple[str, str, str], list[RunScores]] = {}
    for run in runs:
        by_config.setdefault((run.method, run.env, run.setting), []).append(run)
    out = []
    for (method, env, setting), members in by_config.items():
        mean, sd, count = {}, {}, {}
        for key in columns(members):
            values = [r.scores[key] for r in members if isinstance(r.scores.get(key), float)]
            if not values:
                continue
            mean[key], count[key] = statistics.fmean(values), len(values)
            sd[key] = statistics.stdev(values) if len(values) > 1 else 0.0
        out.append(GroupScores(method, env, setting, tuple(members), mean, sd, count))
    return out


def _cell(value: float | str | None) -> str:
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    return f"{value:.3f}" if abs(value) < 100 else f"{value:.1f}"


def run_table(runs: Sequence[RunScores]) -> str:
    """Markdown: a row per run, a column per score some run has (blank where a run has none)."""
    cols = columns(runs)
    lines = ["| run | method | env | seed | " + " | ".join(cols) + " |", "|---" * (4 + len(cols)) + "|"]
    for run in runs:
        env = f"{run.env} ({run.setting})" if run.setting else run.env
        seed = "" if run.seed is None else str(run.seed)
        lines.append(f"| {run.run_id} | {run.method} | {env} | {seed} | "
                     + " | ".join(_cell(run.scores.get(c)) for c in cols) + " |")
    return "\n".join(lines)


def group_table(groups: Sequence[GroupScores]) -> str:
    """Markdown: a row per configuration, each score as mean ± sample sd over its runs (``(n)`` where
    fewer runs than the group's have it)."""
    cols = columns([r for g in groups for r in g.runs])
    lines = ["| method | env | runs | seeds | " + " | ".join(cols) + " |", "|---" * (4 + len(cols)) + "|"]
    for g in groups:
        cells = []
        for c in cols:
            if c not in g.mean:
                cells.append(ERROR if any(r.scores.get(c) == ERROR for r in g.runs) else "")
                continue
            text = _cell(g.mean[c]) + (f" ± {_cell(g.sd[c])}" if g.count[c] > 1 else "")
            cells.append(text + (f" ({g.count[c]})" if g.count[c] < len(g.runs) else ""))
        env = f"{g.env} ({g.setting})" if g.setting else g.env
        seeds = ", ".join(str(r.seed) for r in g.runs if r.seed is not None)
        lines.append(f"| {g.method} | {env} | {len(g.runs)} | {seeds} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(labels: Sequence[str], values: Sequence[dict[str, float]], errors: Sequence[dict[str, float]] | None,
         cols: Sequence[str], path: Path) -> None:
    """One panel per score: a horizontal bar per row (run or configuration), error bars where given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = [c for c in cols if any(c in v for v in values)]
    if not cols:
        raise ValueError("no run has a contract score to plot")
    ncols = min(4, len(cols))
    nrows = math.ceil(len(cols) / ncols)
    label_inches = 0.065 * max(len(label) for label in labels)
    fig, axes = plt.subplots(nrows, ncols, sharey=True, squeeze=False,
                             figsize=(label_inches + 2.8 * ncols, (0.9 + 0.25 * len(labels)) * nrows + 0.5))
    colours = plt.get_cmap("tab10")
    rows = range(len(labels))
    for ax, col in zip(axes.flat, cols):
        y = [i for i in rows if col in values[i]]
        ax.barh(y, [values[i][col] for i in y], color=[colours(i % 10) for i in y],
                xerr=[errors[i].get(col, 0.0) for i in y] if errors is not None else None, capsize=3)
        ax.set_title(col, fontsize=9)
        ax.set_yticks(list(rows), labels, fontsize=7)
        ax.tick_params(axis="x", labelsize=7)
        ax.grid(axis="x", alpha=0.3)
    axes[0][0].invert_yaxis()
    for ax in list(axes.flat)[len(cols):]:
        ax.axis("off")
    fig.suptitle("causeway compare: the results contract's scores" + (" (mean ± sd)" if errors else ""), fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _json_rows(runs: Sequence[RunScores], groups: Sequence[GroupScores] | None) -> dict[str, Any]:
    out: dict[str, Any] = {"columns": columns(runs), "runs": [
        {"path": str(r.path), "run_id": r.run_id, "method": r.method, "env": r.env, "seed": r.seed,
         "setting": r.setting, "scores": r.scores} for r in runs]}
    if groups is not None:
        out["groups"] = [{"method": g.method, "env": g.env, "setting": g.setting,
                          "runs": [r.run_id for r in g.runs], "mean": g.mean, "sd": g.sd, "count": g.count}
                         for g in groups]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="causeway compare", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="finished run directories (or their summary.json files)")
    p.add_argument("--mean", action="store_true",
                   help="one row per configuration (method, env, env options): mean ± sample sd over its runs")
    p.add_argument("--plot", type=Path, help="write a PNG with one panel per score")
    p.add_argument("--json", type=Path, help="write the rows (and groups with --mean) as JSON")
    args = p.parse_args(argv)
    runs, problems = [], []
    for path in args.runs:
        try:
            runs.append(load_run(path))
        except ValueError as exc:
            problems.append(str(exc))
    if problems:
        for problem in problems:
            print(f"causeway compare: {problem}", file=sys.stderr)
        return 2
    cols = columns(runs)
    if not cols:
        print("causeway compare: none of these runs has a score of the results contract "
              f"({', '.join(block for block, _ in CONTRACT)})", file=sys.stderr)
        return 2
    groups = group(runs) if args.mean else None
    print(group_table(groups) if groups is not None else run_table(runs))
    if args.plot is not None:
        if groups is not None:
            labels = [f"{g.method} {g.env}" + (f" {g.setting}" if g.setting else "") + f" (n={len(g.runs)})"
                      for g in groups]
            plot(labels, [g.mean for g in groups], [g.sd for g in groups], cols, args.plot)
        else:
            values = [{k: v for k, v in r.scores.items() if isinstance(v, float)} for r in runs]
            plot([r.run_id for r in runs], values, None, cols, args.plot)
        print(f"causeway compare: wrote {args.plot}", file=sys.stderr)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(_json_rows(runs, groups), indent=1) + "\n")
        print(f"causeway compare: wrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
