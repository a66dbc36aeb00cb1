"""Cost of local graphs (chapter 5.3.1): ELDEN's Jacobians against pCMI's masked passes, as d_S grows.

For one batch of transitions and each number of factors d_S (categorical factors, a categorical
action), this times in one process, CPU seconds of one thread, best of ``--repeats``:

* ``elden``: ELDEN's local graphs, ``|d log p(s^j_{t+1}) / d s^i_t|`` by ``jacrev`` on the 5-member
  attention ensemble (``causal.elden_graphs.local_graphs``);
* ``pcmi_masked``: pCMI the chapter's way on the *same* ensemble: the full pass and one pass per
  dropped input (token ``i`` zeroed), ``d_S + 2`` forward passes batched into one;
* ``pcmi_cdl``: CDL's point-wise CMI (``CDLModel.pointwise_cmi``) with CDL's default widths, whose
  element-wise max makes "drop input i" for every i cost one top-2 over the features.

It prints each time per transition, the ratios pCMI / ELDEN, the parameter counts, and a log-log
slope of each cost against d_S. The chapter says pCMI costs d_S times more than ELDEN: with one
network per output factor, as its Fig. 5.3 draws, pCMI runs ``d_S + 1`` passes of each of ``d_S``
networks and ELDEN one backward pass of each. Our ensemble shares its trunk between outputs, so
both cost about ``d_S`` passes of one network, and this measures the ratio that remains.

    python -m benchmarks.bench_local_graph_cost [--factors 5 10 20 40] [--batch 128] [--repeats 3]
"""
from __future__ import annotations

import argparse
import time
from typing import Callable

import numpy as np
import torch

from causal.cdl import CDLConfig, CDLModel
from causal.elden import ELDENConfig, ELDENModel
from causal.elden_graphs import local_graphs
from causal.factored import FactorLayout

CATEGORIES = 5


def layout(factors: int) -> FactorLayout:
    return FactorLayout(tuple(f"f{i}" for i in range(factors)), ("categorical",) * factors,
                        (CATEGORIES,) * factors, (0.0,) * factors, (1.0,) * factors, "categorical", factors)


def batch(factors: int, size: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    state = torch.randint(0, CATEGORIES, (size, factors), generator=g).float()
    nxt = torch.randint(0, CATEGORIES, (size, factors), generator=g).float()
    return state, torch.randint(0, factors, (size, 1), generator=g).float(), nxt


@torch.no_grad()
def pcmi_masked(model: ELDENModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
    """pCMI on ELDEN's network: ``log p(full) - log p(input i zeroed)`` for every i, ``[B, d_S, d_S + 1]``,
    from one forward pass over the full inputs and the ``d_S + 1`` masked copies."""
    x = model.encode(state, action)
    t = x.shape[1]
    keep = torch.cat([torch.ones(1, t), 1.0 - torch.eye(t)])  # [T + 1, T]: full, then one token dropped
    masked = (keep[:, None, :, None] * x[None]).flatten(0, 1)  # [(T + 1) B, T, W]
    targets = model.targets(state, next_state)
    repeated = type(targets)(*(v.repeat(t + 1, *([1] * (v.dim() - 1))) for v in targets))
    loglik = model.log_likelihood(model(masked), repeated).mean(dim=0).view(t + 1, x.shape[0], -1)
    return (loglik[:1] - loglik[1:]).permute(1, 2, 0)


def cpu_seconds(run: Callable[[], object], repeats: int) -> float:
    run()
    best = float("inf")
    for _ in range(repeats):
        start = time.process_time()
        run()
        best = min(best, time.process_time() - start)
    return best


def measure(factors: int, size: int, repeats: int) -> dict[str, float]:
    torch.manual_seed(0)
    elden, cdl = ELDENModel(layout(factors), ELDENConfig()), CDLModel(layout(factors), CDLConfig())
    s, a, n = batch(factors, size)
    times = {"elden": cpu_seconds(lambda: local_graphs(elden, s, a, n), repeats),
             "pcmi_masked": cpu_seconds(lambda: pcmi_masked(elden, s, a, n), repeats),
             "pcmi_cdl": cpu_seconds(lambda: cdl.pointwise_cmi(s, a, n), repeats)}
    params = {"elden_params": sum(p.numel() for p in elden.parameters()),
              "cdl_params": sum(p.numel() for p in cdl.parameters())}
    return {"factors": factors, **{k: v / size for k, v in times.items()}, **params}


def slope(xs: list[float], ys: list[float]) -> float:
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factors", nargs="+", type=int, default=[5, 10, 20, 40])
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    rows = [measure(f, args.batch, args.repeats) for f in args.factors]
    print(f"CPU ms per transition (one thread, batch {args.batch}, best of {args.repeats}); ratio = pCMI / ELDEN")
    print("| d_S | ELDEN Jacobian | pCMI masked passes (same ensemble) | ratio | pCMI CDL top-2 | ratio | "
          "ELDEN params | CDL params |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['factors']} | {1e3 * r['elden']:.2f} | {1e3 * r['pcmi_masked']:.2f} | "
              f"{r['pcmi_masked'] / r['elden']:.2f} | {1e3 * r['pcmi_cdl']:.2f} | {r['pcmi_cdl'] / r['elden']:.2f} | "
              f"{r['elden_params']:,} | {r['cdl_params']:,} |")
    if len(rows) > 1:
        xs = [r["factors"] for r in rows]
        print("log-log slope against d_S: " + ", ".join(
            f"{k} {slope(xs, [r[k] for r in rows]):.2f}" for k in ("elden", "pcmi_masked", "pcmi_cdl")))


if __name__ == "__main__":
    main()
