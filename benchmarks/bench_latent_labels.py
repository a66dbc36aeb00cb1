"""What FLAM's latent-action labels cost (issue 25 item 6, ``--label-latent-actions``): can one
factor-extractor keep up with the env-workers, and what the labels add to the bus.

One process, one torch thread, no bus: an env-worker core on ``multigrid-agents`` with frames beside its
transitions, and the factor-extractor's labeller holding FLAM weights of the run's default model (the
method's defaults, ``--flam-*``; untrained weights cost the same as trained ones). Per round, the same
number of batches of each:

* the baseline: the worker collecting a batch and packing its frames (``collect`` + ``frames_of``),
  the work an env-worker does per batch besides publishing;
* the labeller: one ``label`` per batch (encode each distinct frame once, the factorizer and the IDM
  over every step's clip).

It prints steps per second of each, their ratio (how many unthrottled workers one labeller serves; the
median over rounds) and the bytes per step of a TransitionBatch, its FrameBatch and its LatentActions
as encoded for the bus.

    python -m benchmarks.bench_latent_labels [--batches 8] [--rounds 3] [--batch-steps 256]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time

import torch

from causal.flam_learner import FLAMRunConfig, FLAMTrainer
from causal.factored import FactorLayout
from causal.method import export_tensors
from proto.codec import encode
from proto.messages import Weights
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.factor_extractor.config import FactorExtractorConfig
from services.factor_extractor.latent import LatentActionLabeller
from services.runtime.config import build_config


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batches", type=int, default=8, help="batches of each side per round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds (the ratio's median is over them)")
    parser.add_argument("--batch-steps", type=int, default=256, help="env steps per batch (the worker's default)")
    parser.add_argument("--slot-dim", type=int, default=FLAMRunConfig.slot_dim, help="FLAM's D (the method's default)")
    parser.add_argument("--out", default="", help="also write the figures as JSON here")
    args = parser.parse_args(argv)
    if min(args.batches, args.rounds, args.batch_steps) < 1:
        parser.error("--batches, --rounds and --batch-steps must be >= 1")
    if args.slot_dim < 4 or args.slot_dim % 4:
        parser.error("--slot-dim must be a positive multiple of 4")
    return args


def labeller_for(worker: EnvWorkerCore, config: FLAMRunConfig) -> LatentActionLabeller:
    """A labeller holding weights of a fresh FLAM model of ``config``, marked past the autoencoder phase."""
    trainer = FLAMTrainer(FactorLayout.from_spec(worker.spec), config, seed=0)
    weights = Weights(model="flam", version=1, config_json=trainer.config_json(),
                      tensors=export_tensors(trainer.model), updates=config.ae_updates + 1)
    labeller = LatentActionLabeller(build_config(FactorExtractorConfig, method="flam", mode="latent-actions"),
                                    worker.spec)
    labeller.load_weights(weights)
    return labeller


def measure(args: argparse.Namespace) -> dict:
    torch.set_num_threads(1)
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, env="multigrid-agents", batch_steps=args.batch_steps,
                                        frames_beside=True))
    labeller = labeller_for(worker, dataclasses.replace(FLAMRunConfig(), slot_dim=args.slot_dim))
    batch = worker.collect()
    frames = worker.frames_of(batch)
    labels = labeller.label(frames)
    sizes = {name: len(encode(message)) / len(batch) for name, message in
             (("transitions", batch), ("frames", frames), ("labels", labels))}
    rounds = []
    for _ in range(args.rounds):
        t0 = time.perf_counter()
        kept = [worker.frames_of(worker.collect()) for _ in range(args.batches)]
        worker_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for batch_frames in kept:
            labeller.label(batch_frames)
        label_s = time.perf_counter() - t0
        steps = args.batches * args.batch_steps
        rounds.append({"worker_steps_per_s": steps / worker_s, "labeller_steps_per_s": steps / label_s,
                       "ratio": worker_s / label_s})
    return {"batch_steps": args.batch_steps, "batches": args.batches, "slot_dim": args.slot_dim,
            "num_slots": labeller.model.lam.config.num_slots, "bytes_per_step": sizes, "rounds": rounds,
            "ratio_median": statistics.median(r["ratio"] for r in rounds)}


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    result = measure(args)
    print(f"multigrid-agents, batches of {result['batch_steps']} steps, FLAM D = {result['slot_dim']}, "
          f"K = {result['num_slots']}, one torch thread")
    for i, r in enumerate(result["rounds"]):
        print(f"round {i}: worker {r['worker_steps_per_s']:,.0f} steps/s, labeller {r['labeller_steps_per_s']:,.0f} "
              f"steps/s, labeller / worker {r['ratio']:.2f}")
    print(f"labeller / worker, median of {len(result['rounds'])} rounds: {result['ratio_median']:.2f} "
          f"(unthrottled workers one labeller keeps up with)")
    b = result["bytes_per_step"]
    print(f"bytes per step on the bus: transitions {b['transitions']:.0f}, frames {b['frames']:.0f}, "
          f"labels {b['labels']:.0f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=2)


if __name__ == "__main__":
    main()
