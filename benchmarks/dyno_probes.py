"""Table 7.5 analogue (chapter 7, Dyn-O): linear probes of colour and position from each object's slot,
its static features, its dynamic features and random features (eqs. 7.3-7.5).

Data: ``chemical-pixels`` sequences (4 objects, 32x32) of ``length`` frames in which each object keeps
its colour and is redrawn at a fresh position every frame (Chemical's own position rule); so colour
is the static property and position the dynamic one. Training sequences come from env seed ``seed``,
probe test rows from ``seed + 10_000``.

Per seed: the frame autoencoder and the annealed slot model are trained as in Table 7.1's analogue,
then frozen. Slots are computed with the renderer's masks given to slot attention, so slot ``1 + j``
is object ``j`` in every frame (the split's losses need one slot per object over time; the chapter's
probes segment objects with SAM). The split (M_c, M_v, M_xi, Disc) is trained on eqs. 7.3-7.5. Then a
linear classifier per feature kind and target is trained on the training sequences' object slots
and scored on the test ones: colour (its 5 values), x and y (10 equal-width bins each).
Budgets are update counts; one torch thread.

    python -m benchmarks.dyno_probes [--seeds 0] [--split-updates 2000] [--out benchmark-results/dyno/probes.json]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.slots_table import Budget as SlotsBudget
from benchmarks.slots_table import train_variant
from benchmarks.seeded_table import table_main
from causal.slot_split import SplitConfig, StaticDynamicSplit, bins, linear_probe
from causal.slots import SlotConfig, SlotModel, fit_autoencoder, token_masks
from envs.chemical_pixels import ChemicalPixelsEnv

EVAL_SEED_OFFSET = 10_000
FEATURES = ("slot", "static", "dynamic", "random")
TARGETS = ("color", "x", "y")


@dataclasses.dataclass(frozen=True)
class Budget:
    num_objects: int = 4
    frame_size: int = 32
    length: int = 8
    train_sequences: int = 500
    test_sequences: int = 150
    ae_updates: int = 300
    slot_updates: int = 1500
    split_updates: int = 2000
    split_batch: int = 16
    log_every: int = 500


def sequences_of(env: ChemicalPixelsEnv, seed: int, count: int, length: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States ``[E, L, 3N]`` (colours held at each sequence's first, positions fresh each frame), frames, labels."""
    env.reset(seed=seed)
    states = env.sample_states(count * length).reshape(count, length, env.num_objects, 3)
    states[..., 0] = states[:, :1, :, 0]
    frames, labels = env.render_states(states.reshape(count * length, -1))
    return states, frames, labels.astype(np.int64)


@torch.no_grad()
def object_slots(model: SlotModel, frames: np.ndarray, labels: np.ndarray) -> torch.Tensor:
    """Slots ``[F, K, d]`` with the masks given, so slot ``1 + j`` is object ``j``."""
    out = []
    for start in range(0, len(frames), 256):
        lab = torch.from_numpy(labels[start : start + 256])
        out.append(model(torch.from_numpy(frames[start : start + 256]), token_masks(lab, model.config.num_slots)).slots)
    return torch.cat(out)


def train_split(split: StaticDynamicSplit, slots: torch.Tensor, budget: Budget, seed: int) -> dict[str, float]:
    """Eqs. 7.3-7.5 on sequences ``[E, L, K, d]``: ``critic_steps`` critic steps (each on its own
    batch), then the static and dynamic parts on the last one."""
    critic = torch.optim.Adam(split.critic.parameters(), lr=split.config.lr)
    parts = [p for name, p in split.named_parameters() if not name.startswith("critic.")]
    features = torch.optim.Adam(parts, lr=split.config.lr)
    batches = torch.Generator().manual_seed(seed)
    losses = None
    for u in range(1, budget.split_updates + 1):
        for _ in range(split.config.critic_steps):
            batch = slots[torch.randint(len(slots), (budget.split_batch,), generator=batches)]
            losses = split.losses(batch)
            critic.zero_grad()
            losses.critic.backward()
            critic.step()
        losses = split.losses(batch)
        features.zero_grad()
        (losses.static + losses.dynamic).backward()
        features.step()
        if u % budget.log_every == 0:
            print(f"  seed {seed} split: update {u} " + " ".join(f"{k} {float(v.detach()):.4f}" for k, v in losses._asdict().items()),
                  file=sys.stderr, flush=True)
    return {k: float(v.detach()) for k, v in losses._asdict().items()} if losses else {}


@torch.no_grad()
def probe_rows(split: StaticDynamicSplit, random: StaticDynamicSplit, slots: torch.Tensor,
               states: np.ndarray) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Per object slot (background left out): each feature kind's inputs and each target's raw values."""
    objects = slots[:, 1:].reshape(-1, slots.shape[-1])
    inputs = {"slot": objects, "static": split.static(objects), "dynamic": split.dynamic(objects),
              "random": random.static(objects)}
    values = torch.from_numpy(states.reshape(-1, 3)).float()
    return inputs, {"color": values[:, 0].long(), "x": values[:, 1], "y": values[:, 2]}


def probes(train: tuple[dict, dict], test: tuple[dict, dict], num_colors: int) -> dict[str, dict[str, float]]:
    """Accuracy of every (feature kind, target) probe; positions in 10 bins over the training range."""
    out: dict[str, dict[str, float]] = {}
    for feature in FEATURES:
        out[feature] = {}
        for target in TARGETS:
            y_train, y_test = train[1][target], test[1][target]
            classes = num_colors if target == "color" else 10
            if target != "color":
                joined = bins(torch.cat([y_train, y_test]))
                y_train, y_test = joined[: len(y_train)], joined[len(y_train):]
            out[feature][target] = linear_probe(train[0][feature], y_train, test[0][feature], y_test, classes)
    return out


def run_seed(seed: int, budget: Budget, split_config: SplitConfig = SplitConfig()) -> dict[str, Any]:
    torch.manual_seed(seed)
    env = ChemicalPixelsEnv(graph="chain", num_objects=budget.num_objects, frame_size=budget.frame_size)
    train = sequences_of(env, seed, budget.train_sequences, budget.length)
    test = sequences_of(env, seed + EVAL_SEED_OFFSET, budget.test_sequences, budget.length)
    frames = (torch.from_numpy(train[1]), torch.from_numpy(train[2]))
    base = SlotModel(SlotConfig(num_slots=budget.num_objects + 1), budget.frame_size)
    ae_loss = fit_autoencoder(base.autoencoder, frames[0], budget.ae_updates, seed=seed)
    slots_budget = SlotsBudget(num_objects=budget.num_objects, frame_size=budget.frame_size,
                               slot_updates=budget.slot_updates, log_every=budget.log_every)
    model, slot_record = train_variant("annealed", seed, slots_budget, base.autoencoder.state_dict(), frames)
    model.eval()
    train_slots = object_slots(model, *train[1:]).view(budget.train_sequences, budget.length, budget.num_objects + 1, -1)
    test_slots = object_slots(model, *test[1:])
    torch.manual_seed(seed)
    split = StaticDynamicSplit(train_slots.shape[-1], split_config)
    random = StaticDynamicSplit(train_slots.shape[-1], split_config)
    started = time.perf_counter()
    final = train_split(split, train_slots, budget, seed)
    split.eval()
    rows_train = probe_rows(split, random, train_slots.flatten(0, 1), train[0])
    rows_test = probe_rows(split, random, test_slots, test[0])
    return {"seed": seed, "autoencoder_mse": ae_loss, "slot_model": slot_record, "split_config": dataclasses.asdict(split_config),
            "split": {"final_losses": final, "train_seconds": time.perf_counter() - started},
            "probes": probes(rows_train, rows_test, env.num_colors)}


def table(results: list[dict[str, Any]]) -> str:
    rows = ["| features | colour (static) | x (dynamic) | y (dynamic) |", "|---|---|---|---|"]
    for feature in FEATURES:
        cells = []
        for target in TARGETS:
            values = [100 * r["probes"][feature][target] for r in results]
            cells.append(f"{np.mean(values):.1f}" + (f" +- {np.std(values):.1f}" if len(values) > 1 else ""))
        rows.append(f"| {feature} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    def split_flags(p: argparse.ArgumentParser) -> None:
        for name in ("disentangle_weight", "lecam_weight"):
            p.add_argument(f"--{name.replace('_', '-')}", type=float, default=getattr(SplitConfig(), name))
        p.add_argument("--critic-steps", type=int, default=SplitConfig().critic_steps,
                       help="critic updates per feature update (eq. 7.5)")
        p.add_argument("--critic-spectral-norm", action="store_true", help="a 1-Lipschitz critic (SplitConfig)")
        p.add_argument("--critic-standardise", action="store_true", help="the critic's inputs standardised (SplitConfig)")

    def one_seed(seed: int, budget: Budget, args: argparse.Namespace, _save: object) -> dict[str, Any]:
        return run_seed(seed, budget, SplitConfig(disentangle_weight=args.disentangle_weight,
                                                  lecam_weight=args.lecam_weight, critic_steps=args.critic_steps,
                                                  critic_spectral_norm=args.critic_spectral_norm,
                                                  critic_standardise=args.critic_standardise))

    table_main(argv, description=__doc__, budget_type=Budget, default_out=Path("benchmark-results/dyno/probes.json"),
               run_seed=one_seed, table=table, add_arguments=split_flags)


if __name__ == "__main__":
    main()
