"""(b) CDL training speed: the batched module against a plain per-factor Python loop, same model.

Both variants share one set of parameters, so they compute the same loss (checked) and the ratio
measures only the batching. Reference point from REFERENCE-NOTES: the authors' code takes 0.28 s per
update for 5 Chemical objects on one thread of these machines.

    python -m benchmarks.bench_cdl_update [--objects 5] [--batch 64] [--width 64] [--updates 20]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from causal.cdl import CDLConfig, CDLModel
from envs import make_env
from causal.factored import FactorLayout

REFERENCE_SECONDS_PER_UPDATE = 0.28


def chemical_batch(objects: int, batch: int) -> tuple[FactorLayout, tuple[torch.Tensor, ...]]:
    env = make_env("chemical", graph="full", num_objects=objects)
    spec = env.unwrapped.env_spec()
    obs, _ = env.reset(seed=0)
    states, actions, nexts = [], [], []
    for _ in range(batch):
        a = env.action_space.sample()
        nxt, *_ = env.step(a)
        states.append(obs), actions.append([a]), nexts.append(nxt)
        obs = nxt
    as_tensor = lambda x: torch.from_numpy(np.asarray(x, dtype=np.float32))  # noqa: E731
    return FactorLayout.from_spec(spec), (as_tensor(states), as_tensor(actions), as_tensor(nexts))


def loop_nll(model: CDLModel, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
             drop: torch.Tensor) -> torch.Tensor:
    """Eq. 3.3's full and dropped-input terms with a Python loop over outputs j and inputs i."""
    codec, n = model.codec, model.num_outputs
    cats, conts = codec.categories(state), codec.continuous_values(state)
    act = action[:, 0].long()
    groups = [(model.cat_features, lambda k: torch.nn.functional.one_hot(cats[:, k], codec.max_cat).float(), len(codec.cat_factors)),
              (model.cont_features, lambda k: conts[:, k], len(codec.cont_factors)),
              (model.action_features, lambda k: torch.nn.functional.one_hot(act, model.layout.action_size).float(), 1)]
    outs = []
    for j in range(n):
        feats = []
        for group, inputs, count in groups:
            for k in range(count):
                h = torch.relu(inputs(k) @ group.w1[j, k] + group.b1[j, k])
                feats.append(h @ group.w2[j * count + k] + group.b2[j * count + k])
        stacked = torch.stack(feats)
        full = stacked.max(dim=0).values
        keep = torch.arange(len(feats))[:, None] != drop[j, 0, :, 0][None, :]
        dropped = stacked.masked_fill(~keep[..., None], float("-inf")).max(dim=0).values
        outs.append(torch.stack([full, dropped]))
    return model.nll(model.predict(torch.stack(outs)), state, next_state)


def batched_nll(model: CDLModel, state, action, next_state, drop) -> torch.Tensor:
    from causal.cdl import _MaxAndDropOne
    feats = model.features(state, action)
    return model.nll(model.predict(torch.cat(list(_MaxAndDropOne.apply(feats, drop)), dim=1)), state, next_state)


def seconds_per_update(fn, model, batch, drop, updates: int, rounds: int = 5) -> float:
    """Best of ``rounds`` timings of ``updates`` Adam steps (the least disturbed by other processes)."""
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step() -> None:
        loss = fn(model, *batch, drop).mean(dim=2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()

    step()
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(updates):
            step()
        best = min(best, (time.perf_counter() - t0) / updates)
    return best


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", type=int, default=5)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--width", type=int, default=64, help="feature hidden = feature dim = head hidden")
    p.add_argument("--updates", type=int, default=20)
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    layout, batch = chemical_batch(args.objects, args.batch)
    model = CDLModel(layout, CDLConfig(feature_hidden=args.width, feature_dim=args.width, predictor_hidden=args.width))
    drop = torch.randint(0, model.num_inputs, (model.num_outputs, 1, args.batch, 1))
    with torch.no_grad():
        torch.testing.assert_close(loop_nll(model, *batch, drop), batched_nll(model, *batch, drop), rtol=1e-4, atol=1e-4)
    loop = seconds_per_update(loop_nll, model, batch, drop, max(3, args.updates // 4), rounds=3)
    batched = seconds_per_update(batched_nll, model, batch, drop, args.updates)
    params = sum(p.numel() for p in model.parameters())
    print(f"CDL update, {args.objects} objects ({model.num_outputs} factors, {params:,} parameters), batch {args.batch}, 1 thread")
    print(f"  per-factor loop : {loop * 1000:8.1f} ms/update")
    print(f"  batched module  : {batched * 1000:8.1f} ms/update")
    print(f"  speed-up batched/loop           : {loop / batched:6.1f}x")
    print(f"  speed-up vs reference 0.28 s    : {REFERENCE_SECONDS_PER_UPDATE / batched:6.1f}x")


if __name__ == "__main__":
    main()
