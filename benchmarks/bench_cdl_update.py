"""(b) CDL update rate: Causeway's trainer against the authors' code, like for like, and the batched
module against a per-factor Python loop over the same parameters.

What each side does in one update (batch 64, one thread, Chemical ``full``):

* the authors' code, its defaults: 64-wide feature networks (input -> 64 -> 64) per (output, input),
  64-wide heads (64 -> 64 -> 64 -> out), **2-step** prediction, full and drop-one terms every update,
  the causal term on 9 of 10 updates, Python loops over factor pairs. Timed side by side on this kind of
  machine with no other load (median of 3 runs; issue 26): **0.150 s** at 5 objects, **0.475 s** at 10;
  with **1-step** prediction 0.079 s / 0.277 s. The older figure of 0.28 s (5 objects, REFERENCE-NOTES)
  was measured under load.
* Causeway, its defaults (``CDLTrainer`` with ``CDLConfig()``): 32-wide feature networks, 32-wide
  features, 64-wide heads, 1-step prediction, full and drop-one terms every update, the causal term
  every 10th (``causal_every=10``); gradient clipping and fused Adam included.
* Causeway at the reference widths: feature networks, features and heads 64 wide; causal term every 10th.
* Causeway like for like: the reference widths with the causal term on every update: the work of the
  authors' 1-step update (same widths, one step, every term every update).
* The same two with ``train_precision="bf16"``: the same work with the matrix products in bfloat16
  (weights, aggregation, losses and Adam in fp32; ``CDLConfig.train_precision``). Not the authors'
  arithmetic, so its ratio to their code is printed apart, beside its ratio to the fp32 setting of
  this run. It pays on CPUs with AVX512-BF16 (this machine's AMD EPYC has it); elsewhere bf16 products
  are emulated and can be slower than fp32.

Causeway's causal term uses Chemical ``full``'s true graph as its parents (``--parents true``, what a
trained run's evaluator gives it): the heads run only on the rows whose dropped or causal aggregate
differs from the full one, so with every input a parent (``--parents all``, a fresh trainer's) the
causal term would cost nothing and flatter the ratio.

Ratios: each side's defaults (authors' defaults / Causeway's), equal widths (authors' defaults /
Causeway at reference widths), like for like (authors' 1-step / Causeway like for like). The authors'
figures exist for 5 and 10 objects only; Causeway's are measured here, in this run (median of
``--rounds`` rounds of ``--updates`` updates on one fixed batch).

The loop baseline (same run) checks that the batched module computes the loop's full and drop-one
terms and measures what the batching alone buys, at ``--width``.

    python -m benchmarks.bench_cdl_update [--objects 5] [--batch 64] [--width 64] [--updates 20] [--device cpu]
        [--parents true|all]
    python -m benchmarks.bench_cdl_update --objects 10 --profile [--precision bf16]   # where a like-for-like update's time goes
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch

from causal.cdl import TRAIN_PRECISIONS, CDLConfig, CDLModel
from causal.cdl_trainer import CDLTrainer
from envs import make_env
from causal.factored import FactorLayout

AUTHORS_SECONDS_PER_UPDATE = {5: {"defaults": 0.150, "one_step": 0.079}, 10: {"defaults": 0.475, "one_step": 0.277}}
"""The authors' code, seconds per update at batch 64 on one thread, idle machine, median of 3 runs (issue 26)."""
REFERENCE_WIDTHS = dict(feature_hidden=64, feature_dim=64, predictor_hidden=64)
SETTINGS = {"defaults": CDLConfig(), "reference widths": CDLConfig(**REFERENCE_WIDTHS),
            "like for like": CDLConfig(**REFERENCE_WIDTHS, causal_every=1),
            "defaults, bf16": CDLConfig(train_precision="bf16"),
            "like for like, bf16": CDLConfig(**REFERENCE_WIDTHS, causal_every=1, train_precision="bf16")}
"""Causeway's trainer settings timed (see the module's docstring for the work each does)."""


def true_parents(objects: int) -> np.ndarray:
    """Chemical ``full``'s one-step graph [d_S, d_S + 1]: the parents a trained run's causal term uses."""
    return make_env("chemical", graph="full", num_objects=objects).unwrapped.global_graph.astype(bool)


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
    from causal.cdl_max import _MaxAndDropOne
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


def trainer_seconds(layout: FactorLayout, cfg: CDLConfig, batch: tuple[torch.Tensor, ...], updates: int,
                    rounds: int, device: torch.device, parents: np.ndarray | None = None) -> float:
    """Median over ``rounds`` of the seconds per ``CDLTrainer.update`` (``updates`` in a row, whole
    causal-term cycles) on one fixed batch; the causal term's ``parents`` (None: every input)."""
    trainer = CDLTrainer(layout, cfg, seed=0)
    if parents is not None:
        trainer.set_parents(parents)
    trainer.to(device)
    batch = tuple(t.to(device) for t in batch)
    updates = max(updates, cfg.causal_every) // cfg.causal_every * cfg.causal_every
    for _ in range(cfg.causal_every):
        trainer.update(*batch)
    times = []
    for _ in range(rounds):
        _sync(device)
        t0 = time.perf_counter()
        for _ in range(updates):
            trainer.update(*batch)
        _sync(device)
        times.append((time.perf_counter() - t0) / updates)
    return statistics.median(times)


def profile_like_for_like(layout: FactorLayout, batch: tuple[torch.Tensor, ...], parents: np.ndarray | None,
                          updates: int = 10, setting: str = "like for like") -> None:
    """Where a like-for-like update spends its time: torch's operator profile, by self CPU time."""
    from torch.profiler import ProfilerActivity, profile

    trainer = CDLTrainer(layout, SETTINGS[setting], seed=0)
    if parents is not None:
        trainer.set_parents(parents)
    for _ in range(3):
        trainer.update(*batch)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(updates):
            trainer.update(*batch)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", type=int, default=5)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--width", type=int, default=64, help="loop baseline: feature hidden = feature dim = head hidden")
    p.add_argument("--updates", type=int, default=20, help="updates per timed round")
    p.add_argument("--rounds", type=int, default=3, help="timed rounds; the median is reported")
    p.add_argument("--device", default="cpu", help="where Causeway's trainer runs (cpu, cuda)")
    p.add_argument("--no-loop", action="store_true", help="skip the per-factor loop baseline")
    p.add_argument("--profile", action="store_true", help="only print torch's operator profile of 10 like-for-like updates")
    p.add_argument("--precision", choices=TRAIN_PRECISIONS, default="fp32", help="--profile: the products' precision")
    p.add_argument("--parents", choices=["true", "all"], default="true",
                   help="the causal term's parents: Chemical full's true graph (a trained run's; default) or every "
                        "input (a fresh trainer's, where the causal aggregate is the full one and costs nothing)")
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    layout, batch = chemical_batch(args.objects, args.batch)
    parents = true_parents(args.objects) if args.parents == "true" else None
    if args.profile:
        profile_like_for_like(layout, batch, parents, setting="like for like" + (", bf16" if args.precision == "bf16" else ""))
        return
    model = CDLModel(layout, CDLConfig(feature_hidden=args.width, feature_dim=args.width, predictor_hidden=args.width))
    print(f"CDL update, {args.objects} objects ({model.num_outputs} factors), batch {args.batch}, 1 thread, "
          f"Causeway on {args.device}")
    if not args.no_loop:
        drop = torch.randint(0, model.num_inputs, (model.num_outputs, 1, args.batch, 1))
        with torch.no_grad():
            torch.testing.assert_close(loop_nll(model, *batch, drop), batched_nll(model, *batch, drop), rtol=1e-4, atol=1e-4)
        loop = seconds_per_update(loop_nll, model, batch, drop, max(3, args.updates // 4), rounds=3)
        batched = seconds_per_update(batched_nll, model, batch, drop, args.updates)
        params = sum(p.numel() for p in model.parameters())
        print(f"  full + drop-one terms at width {args.width} ({params:,} parameters), plain Adam:")
        print(f"    per-factor loop : {loop * 1000:8.1f} ms/update")
        print(f"    batched module  : {batched * 1000:8.1f} ms/update   ({loop / batched:.1f}x the loop)")
    device = torch.device(args.device)
    measured = {name: trainer_seconds(layout, cfg, batch, args.updates, args.rounds, device, parents)
                for name, cfg in SETTINGS.items()}
    print("  CDLTrainer.update (eq. 3.3, clipping, fused Adam), median of rounds:")
    for name, seconds in measured.items():
        print(f"    Causeway, {name:<21}: {seconds * 1000:8.1f} ms/update")
    authors = AUTHORS_SECONDS_PER_UPDATE.get(args.objects)
    if authors is None:
        print(f"  the authors' code was timed at {sorted(AUTHORS_SECONDS_PER_UPDATE)} objects only: no ratio")
        return
    print(f"  the authors' code (issue 26, idle machine): defaults {authors['defaults']:.3f} s, "
          f"1-step {authors['one_step']:.3f} s")
    load = os.getloadavg()[0]
    if load > 1.5:
        print(f"  WARNING: load average {load:.1f} here: the ratios below compare a loaded run with the authors' "
              f"idle figures (run on an idle machine)")
    ratios = {"each side's defaults": authors["defaults"] / measured["defaults"],
              "equal widths (authors' defaults)": authors["defaults"] / measured["reference widths"],
              "like for like (1-step, every term)": authors["one_step"] / measured["like for like"]}
    for name, ratio in ratios.items():
        print(f"    speed-up, {name:<35}: {ratio:6.1f}x")
    print("  bf16 products (not the authors' arithmetic; CDLConfig.train_precision):")
    for name in ("defaults", "like for like"):
        print(f"    {name + ', bf16':<22}: {measured[name] / measured[name + ', bf16']:5.2f}x the fp32 setting of this run, "
              f"{authors['defaults' if name == 'defaults' else 'one_step'] / measured[name + ', bf16']:5.1f}x the authors' code")


if __name__ == "__main__":
    main()
