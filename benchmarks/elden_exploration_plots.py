"""Figures and the table of :mod:`benchmarks.elden_exploration`: a learning curve per run, one
comparison per env (mean +- standard error over seeds, one line per reward), final stage counts."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

TITLES = {"none": "PPO", "elden": "ELDEN", "curiosity": "Dynamics curiosity", "disagreement": "Disagreement"}


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_run(result: dict[str, Any], path: Path) -> None:
    """Normalised stage count and mean intrinsic reward against env steps, for one run."""
    plt = _pyplot()
    cfg, curve = result["config"], result["curve"]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6, 5), sharex=True)
    top.plot(curve["env_steps"], curve["stages"], label="normalised stage count")
    top.plot(curve["env_steps"], curve["success"], label="success rate", alpha=0.6)
    top.set_ylim(0, 1.02)
    top.legend(loc="upper left")
    top.set_title(f"{cfg['env']}: {TITLES[cfg['reward']]}, seed {cfg['seed']}")
    bottom.plot(curve["env_steps"], curve["intrinsic_mean"], color="tab:green")
    if cfg["reward"] == "elden":
        bottom.axvline(cfg["warmup_steps"], color="grey", linestyle=":", label="end of warm-up")
        bottom.legend(loc="upper right")
    bottom.set_ylabel("mean eta x r_intrinsic")
    bottom.set_xlabel("env steps")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def by_reward(results: list[dict[str, Any]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per reward: env steps ``[U]`` and every seed's stage counts ``[seeds, U]`` (cut to the shortest)."""
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for reward in dict.fromkeys(r["config"]["reward"] for r in results):
        curves = [r["curve"] for r in results if r["config"]["reward"] == reward]
        length = min(len(c["env_steps"]) for c in curves)
        out[reward] = (np.asarray(curves[0]["env_steps"][:length]),
                       np.asarray([c["stages"][:length] for c in curves], dtype=float))
    return out


def plot_comparison(results: list[dict[str, Any]], path: Path) -> None:
    """One env: mean +- standard error over seeds of the normalised stage count, one line per reward."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for reward, (steps, stages) in by_reward(results).items():
        mean = stages.mean(axis=0)
        se = stages.std(axis=0, ddof=1) / np.sqrt(len(stages)) if len(stages) > 1 else np.zeros_like(mean)
        ax.plot(steps, mean, label=f"{TITLES[reward]} ({len(stages)} seeds)")
        ax.fill_between(steps, mean - se, mean + se, alpha=0.2)
    ax.set_xlabel("env steps")
    ax.set_ylabel("normalised stage count")
    ax.set_ylim(0, 1.02)
    ax.set_title(f"{results[0]['config']['env']}: mean ± s.e. over seeds")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def summary_markdown(results: list[dict[str, Any]]) -> str:
    """Final normalised stage count and success (mean ± sd over seeds) per reward, and the mean over
    the second half of training (a steadier reading of the curve)."""
    lines = ["| reward | seeds | final stage count | final success | stage count, second half | CPU s per run |",
             "|---|---|---|---|---|---|"]
    for reward in dict.fromkeys(r["config"]["reward"] for r in results):
        mine = [r for r in results if r["config"]["reward"] == reward]
        final = np.array([r["final_stages"] for r in mine])
        success = np.array([r["final_success"] for r in mine])
        half = np.array([np.mean(r["curve"]["stages"][len(r["curve"]["stages"]) // 2:]) for r in mine])
        cpu = np.mean([r["cpu_s"] for r in mine])
        lines.append(f"| {TITLES[reward]} | {len(mine)} | {final.mean():.3f} ± {final.std():.3f} | "
                     f"{success.mean():.2f} ± {success.std():.2f} | {half.mean():.3f} ± {half.std():.3f} | {cpu:.0f} |")
    return "\n".join(lines) + "\n"
