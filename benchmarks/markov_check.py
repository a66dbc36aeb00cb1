"""Is an environment Markov in its factors? The previous action's share of what ``(s_t, a_t)`` leaves
unexplained in each factor's next value (issue 19's block and tool-use graphs).

Every causal method here assumes that ``s_{t+1}`` depends on ``(s_t, a_t)`` alone (chapter 3's
Assumption 2). Where a factor carries hidden state (a velocity the state has no factor for), the
previous action predicts the next value beyond ``(s_t, a_t)``. Chapter 4's controllable distractors
are projections of that previous action, so on such an env they *are* informative about the scene,
and a learned graph gives them edges the Markov truth does not have.

The check: collection-policy transitions (:class:`benchmarks.cbm_graph_table.CollectionPolicy`, the
data Table 4.1's benchmark trains on), distractors off, then two MLPs of the same size and schedule
fitted to every factor's change ``s_{t+1} - s_t`` (standardised): one from ``(s_t, a_t)``, one from
``(s_t, a_t, a_{t-1})``, on the steps that have a previous action in their episode; held-out R^2 per
factor for both, and ``gain = (R^2_prev - R^2) / (1 - R^2)``, the share of the unexplained variance
the previous action explains (near 0 on a Markov env; the fit's own noise puts a few hundredths
there). ``nats`` is the same comparison on the scale of a CMI edge: ``0.5 ln(MSE / MSE_prev)`` of the
held-out errors, the conditional mutual information a Gaussian residual would give (negative where
the fit with ``a_{t-1}`` does worse: the fit's noise). Where ``(s_t, a_t)`` explain nearly everything,
a gain too small for R^2 to show is large in nats (R^2 0.995 -> 0.996 is 0.11 nats, five times
CBM's 0.02-nat edge threshold), so this column says whether the check can resolve what a threshold
counts as an edge. Factors whose change is constant on the training rows (a cube nothing touched) are marked
``constant`` instead. Writes ``<out>/markov.json`` and ``<out>/markov.png`` (R^2 per factor, without
and with the previous action); prints a table.

    python -m benchmarks.markov_check --env block --steps 6000
    python -m benchmarks.markov_check --env block --steps 6000 --control-freq 5 --out benchmark-results/markov-block-5hz
    python -m benchmarks.markov_check --env manipulation --steps 6000 --out benchmark-results/markov-manipulation
    python -m benchmarks.markov_check --env block --steps 6000 --velocities --out benchmark-results/markov-block-vel
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

CONSTANT_STD = 1e-6
"""A factor whose change has at most this standard deviation on the training rows is ``constant``."""
NOTHING_LEFT = 0.02
"""No ``gain`` where ``(s_t, a_t)`` leave less than this share of the variance: the ratio is then the
fit's noise over a near-zero remainder."""


def predictability(state: np.ndarray, action: np.ndarray, next_state: np.ndarray, first: np.ndarray, *,
                   hidden: int = 128, updates: int = 4000, batch: int = 256, lr: float = 1e-3,
                   heldout_share: float = 0.2, seed: int = 0,
                   progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Held-out R^2 of each factor's change from ``(s_t, a_t)`` and from ``(s_t, a_t, a_{t-1})``.

    ``state``, ``next_state`` are ``[T, d]``, ``action`` ``[T, m]``, ``first`` ``[T]`` marks the first
    step of each episode (it has no previous action and is left out). Rows are split at random (seeded)
    into fitted and held out. Returns ``r2``, ``r2_prev``, ``gain`` (lists over factors, ``None`` where
    ``constant``; ``gain`` also where ``R^2 > 1 -`` :data:`NOTHING_LEFT`), ``constant`` and the row counts.
    ``progress``, if given, receives a line per tenth of each fit's updates."""
    state, next_state = np.asarray(state, np.float64), np.asarray(next_state, np.float64)
    action, first = np.asarray(action, np.float64), np.asarray(first, bool)
    if not (len(state) == len(action) == len(next_state) == len(first)):
        raise ValueError("state, action, next_state and first must have the same number of rows")
    action = action.reshape(len(state), -1)
    previous = np.zeros_like(action)
    previous[1:] = action[:-1]
    rows = np.flatnonzero(~first)
    rows = rows[rows > 0]
    if len(rows) < 10:
        raise ValueError(f"need at least 10 steps with a previous action, got {len(rows)}")
    rng = np.random.default_rng(seed)
    rows = rng.permutation(rows)
    cut = int(round(len(rows) * (1.0 - heldout_share)))
    fit_rows, test_rows = rows[:cut], rows[cut:]
    delta = next_state - state
    spread = delta[fit_rows].std(axis=0)
    constant = spread <= CONSTANT_STD
    target = (delta - delta[fit_rows].mean(axis=0)) / np.where(constant, 1.0, spread)

    def standardised(x: np.ndarray) -> np.ndarray:
        return (x - x[fit_rows].mean(axis=0)) / (x[fit_rows].std(axis=0) + 1e-6)

    base = np.concatenate([standardised(state), standardised(action)], axis=1)
    with_previous = np.concatenate([base, standardised(previous)], axis=1)
    residual = {name: _fit(x, target, fit_rows, test_rows, hidden, updates, batch, lr, seed, progress, f"fit {name}")
                for name, x in (("r2", base), ("r2_prev", with_previous))}
    variance = target[test_rows].var(axis=0)
    out: dict[str, Any] = {"constant": constant.tolist(), "fitted_rows": int(len(fit_rows)),
                           "heldout_rows": int(len(test_rows))}
    for name, mse in residual.items():
        out[name] = [None if c or v <= 0 else float(1.0 - m / v) for c, m, v in zip(constant, mse, variance)]
    out["gain"] = [None if a is None or b is None or 1.0 - a < NOTHING_LEFT else float((b - a) / (1.0 - a))
                   for a, b in zip(out["r2"], out["r2_prev"])]
    out["nats"] = [None if c or v <= 0 or m <= 0 or mp <= 0 else float(0.5 * np.log(m / mp))
                   for c, m, mp, v in zip(constant, residual["r2"], residual["r2_prev"], variance)]
    return out


def _fit(x: np.ndarray, y: np.ndarray, fit_rows: np.ndarray, test_rows: np.ndarray, hidden: int,
         updates: int, batch: int, lr: float, seed: int,
         progress: Callable[[str], None] | None = None, label: str = "fit") -> np.ndarray:
    """Held-out squared error per output of a two-hidden-layer MLP fitted by Adam on ``fit_rows``;
    ``progress("<label>: <done>/<updates> updates")`` after each tenth of the updates."""
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    xt, yt = torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(y, dtype=torch.float32)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], hidden), torch.nn.ReLU(),
                              torch.nn.Linear(hidden, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, y.shape[1]))
    optimiser = torch.optim.Adam(net.parameters(), lr=lr)
    fit_x, fit_y = xt[fit_rows], yt[fit_rows]
    every = max(1, updates // 10)
    for done in range(1, updates + 1):
        pick = torch.randint(len(fit_rows), (min(batch, len(fit_rows)),), generator=generator)
        loss = (net(fit_x[pick]) - fit_y[pick]).pow(2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if progress is not None and (done % every == 0 or done == updates):
            progress(f"{label}: {done}/{updates} updates")
    with torch.no_grad():
        return (net(xt[test_rows]) - yt[test_rows]).pow(2).mean(dim=0).numpy()


def collect_episodes(env_name: str, env_kwargs: dict[str, Any], steps: int, seed: int
                     ) -> tuple[tuple[str, ...], dict[str, np.ndarray]]:
    """``steps`` transitions of the collection policy Table 4.1's benchmark uses
    (:func:`benchmarks.cbm_graph_table.collect`, with ``first``); a categorical action one-hot."""
    from benchmarks.cbm_graph_table import collect

    print(f"collecting {steps} steps of {env_name}", file=sys.stderr, flush=True)
    spec, data = collect(env_kwargs, steps, seed, env_name)
    if spec.action_kind == "categorical":  # a choice is no scale
        data["action"] = np.eye(spec.action_size)[data["action"][:, 0].astype(int)]
    return tuple(spec.factor_names), data


def table(names: tuple[str, ...], result: dict[str, Any]) -> str:
    def cell(value: float | None) -> str:
        return "-" if value is None else f"{value:.3f}"

    lines = ["| factor | R^2 from (s_t, a_t) | R^2 with a_{t-1} | share of the rest a_{t-1} explains | in nats |",
             "|---|---|---|---|---|"]
    nats = result.get("nats", [None] * len(names))  # files written before the column have none
    for i, name in enumerate(names):
        if result["constant"][i]:
            lines.append(f"| {name} | constant | constant | - | - |")
        else:
            lines.append(f"| {name} | {cell(result['r2'][i])} | {cell(result['r2_prev'][i])} | {cell(result['gain'][i])} "
                         f"| {'-' if nats[i] is None else f'{nats[i]:+.3f}'} |")
    return "\n".join(lines)


def plot(names: tuple[str, ...], result: dict[str, Any], path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [i for i in range(len(names)) if not result["constant"][i] and result["r2"][i] is not None]
    x = np.arange(len(shown))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.45 * len(shown) + 2), 3.6))
    ax.bar(x - 0.2, [result["r2"][i] for i in shown], 0.4, label="from (s_t, a_t)")
    ax.bar(x + 0.2, [result["r2_prev"][i] for i in shown], 0.4, label="with a_{t-1}")
    ax.set_xticks(x, [names[i] for i in shown], rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("held-out R^2 of the change")
    ax.set_ylim(min(0.0, *(result["r2"][i] for i in shown)) if shown else 0.0, 1.0)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="block", choices=("block", "tool-use", "manipulation", "chemical-distractors"),
                   help="manipulation: chapter 3's scene (uniformly random actions; it has no distractors)")
    p.add_argument("--steps", type=int, default=6000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--control-freq", type=int, default=0, help="policy steps per second (0: the env's 10)")
    p.add_argument("--updates", type=int, default=4000, help="Adam updates per fit")
    p.add_argument("--velocities", action="store_true",
                   help="the robosuite scenes with velocity factors (eef, fingers, movable bodies)")
    p.add_argument("--out", type=Path, default=Path("benchmark-results/markov"))
    args = p.parse_args(argv)
    if args.steps < 50:
        p.error("--steps must be at least 50")
    if args.control_freq and args.env == "chemical-distractors":
        p.error("--control-freq applies to the robosuite scenes (block, tool-use, manipulation) only")
    if args.velocities and args.env == "chemical-distractors":
        p.error("--velocities applies to the robosuite scenes (block, tool-use, manipulation) only")
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    env_kwargs: dict[str, Any] = {}
    if args.env != "manipulation":
        env_kwargs = {"distractors": "0,0", "task": {"block": "pick", "tool-use": "series"}.get(args.env, "match")}
    if args.control_freq:
        env_kwargs["control_freq"] = args.control_freq
    if args.velocities:
        env_kwargs["velocities"] = True
    names, data = collect_episodes(args.env, env_kwargs, args.steps, args.seed)
    result = predictability(data["state"], data["action"], data["next_state"], data["first"],
                            updates=args.updates, seed=args.seed,
                            progress=lambda line: print(line, file=sys.stderr, flush=True))
    title = (f"{args.env}, {args.steps} steps, seed {args.seed}" + (f", {args.control_freq} Hz" if args.control_freq else "")
             + (", velocity factors" if args.velocities else ""))
    (args.out / "markov.json").write_text(json.dumps({"args": vars(args) | {"out": str(args.out)},
                                                       "factor_names": names, **result}, indent=1))
    plot(names, result, args.out / "markov.png", title)
    print(table(names, result))


if __name__ == "__main__":
    main()
