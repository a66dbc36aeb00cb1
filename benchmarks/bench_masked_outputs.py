"""Causal-mode forward for planning and rollouts: all-pairs masking vs running only the kept pairs.

``CDLModel.masked_outputs`` evaluates just the (output, input) feature networks the graph keeps; the
baseline, measured in the same run, evaluates every pair and masks the rest to -inf before the max
(what ``causal.planning.cdl_outputs`` did before). Both give the same outputs (checked here too).

    python -m benchmarks.bench_masked_outputs [--objects 10] [--graph full] [--batch 1024] [--repeats 5]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from causal.cdl import CDLConfig, CDLModel
from causal.factored import FactorLayout
from envs.chemical import ChemicalEnv


def all_pairs(model: CDLModel, state: torch.Tensor, action: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    keep = model.to_group_order(mask)
    feats = model.features(state, action).masked_fill(~keep[:, :, None, None], float("-inf"))
    return model.predict(feats.amax(dim=1, keepdim=True))[:, 0]


def best_of(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return min(times)


def main(argv: list[str] | None = None) -> dict[str, float]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--objects", type=int, default=10)
    p.add_argument("--graph", default="full")
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    env = ChemicalEnv(graph=args.graph, num_objects=args.objects)
    model = CDLModel(FactorLayout.from_spec(env.env_spec()), CDLConfig()).eval()
    mask = torch.from_numpy(env.global_graph.astype(bool))
    rng = np.random.default_rng(0)
    state = torch.from_numpy(np.stack([env.reset(seed=int(s))[0] for s in rng.integers(0, 1 << 30, args.batch)])
                             .astype(np.float32))
    action = torch.from_numpy(rng.integers(0, env.action_space.n, (args.batch, 1)).astype(np.float32))
    with torch.no_grad():
        torch.testing.assert_close(model.masked_outputs(state, action, mask), all_pairs(model, state, action, mask),
                                   rtol=1e-5, atol=1e-6)
        dense = best_of(lambda: all_pairs(model, state, action, mask), args.repeats)
        sparse = best_of(lambda: model.masked_outputs(state, action, mask), args.repeats)
    kept, total = int(mask.sum()), mask.numel()
    print(f"causal-mode forward, Chemical {args.graph}, {args.objects} objects, batch {args.batch}, 1 thread, "
          f"graph keeps {kept} of {total} pairs")
    print(f"  all pairs, masked (baseline) : {dense * 1000:8.1f} ms")
    print(f"  kept pairs only              : {sparse * 1000:8.1f} ms")
    print(f"  speed-up                     : {dense / sparse:6.1f}x")
    return {"all_pairs_s": dense, "kept_pairs_s": sparse, "speedup": dense / sparse}


if __name__ == "__main__":
    main()
