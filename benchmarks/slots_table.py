"""Table 7.1 analogue (chapter 7, Dyn-O): FG-ARI of slot masks against the renderer's exact masks.

For each seed: frames of ``--env`` train the frame
autoencoder (Enc/Dec of eq. 7.1, then frozen and shared by the three variants, as the Cosmos
tokenizer is in the chapter), then slot attention and the slot decoder are trained on eq. 7.1 three
times, with the same initial weights and batches:

- ``annealed`` (Dyn-O): the masks are dropped with probability log(1 + u) / log(1 + U);
- ``none`` (SOLV): never masks;
- ``always`` (the oracle): always masks.

Each is scored by FG-ARI on frames from an unseen seed without masks at inference (the chapter's
question: does the slot binding survive without the segmenter?), and the oracle also with its masks
at inference (the chapter's definition of the oracle row). FG-ARI is blind to which slot holds which
object; the slot identity (the share of foreground pixels in the slot the prior binds their object
to) says whether slot ``1 + j`` is object ``j`` in every frame, which a slot-wise causal model needs. Budgets are update counts, so a loaded
machine gives the same numbers, only later; one torch thread.

``--env chemical-pixels`` (default): states drawn as ``reset`` draws them (a fresh layout each), with
``--num-objects`` objects; ``--env chemical-pixels-two-tone``: the same with each shape's lower half
drawn in one grey shared by all objects (``ChemicalPixelsEnv.two_tone``: objects of two parts, where
unsupervised slots may group the parts by colour across objects). ``--env sprites``: the bigfish-like sprite game (``envs.sprites``), frames
of uniformly random play (:func:`envs.sprites.record_frames`), ``--num-objects`` objects = the agent
and ``num_objects - 1`` fish; overlapping multi-coloured sprites on a textured background, the
harder scene the Chemical rows lack.

    python -m benchmarks.slots_table [--env sprites] [--seeds 0 1 2] [--slot-updates 1500] [--out benchmark-results/slots/table.json]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from benchmarks.seeded_table import table_main
from causal.fg_ari import fg_ari
from causal.slots import MASK_ASSIGNMENTS, TOKEN_MASKS, SlotConfig, SlotModel, SlotTrainer, fit_autoencoder, token_masks
from envs.chemical_pixels import ChemicalPixelsEnv
from envs.sprites import SpritesEnv, record_frames

VARIANTS = ("annealed", "none", "always")
ENVS = ("chemical-pixels", "chemical-pixels-two-tone", "sprites")
"""The rendered environments ``--env`` takes."""
EVAL_SEED_OFFSET = 10_000
"""Evaluation frames come from env seed ``seed + EVAL_SEED_OFFSET``: unseen in training."""


@dataclasses.dataclass(frozen=True)
class Budget:
    """What one seed trains on and for how long (update counts, not seconds)."""

    num_objects: int = 4
    frame_size: int = 32
    train_frames: int = 4096
    eval_frames: int = 512
    ae_updates: int = 300
    slot_updates: int = 1500
    log_every: int = 250
    num_slots: int = 0
    """K; 0: one per object and one for the background. The chapter's K is far above the object count
    (31 or 47 slots on Procgen; unused slots stay free), and the failure it names for unsupervised slots,
    one object split over several, needs spare slots to happen (on the sprite game at 32x32 it did not:
    docs/results.md, "On the sprite game")."""

    def __post_init__(self) -> None:
        if self.num_slots and self.num_slots < self.num_objects + 1:
            raise ValueError(f"--num-slots {self.num_slots} < {self.num_objects + 1}: one slot per object and "
                             "one for the background at least")

    @property
    def slots(self) -> int:
        """K as trained: ``num_slots``, or ``num_objects + 1`` where it is 0."""
        return self.num_slots or self.num_objects + 1


def frames_of(env: ChemicalPixelsEnv, seed: int, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` frames and label maps from ``env`` reset with ``seed``."""
    env.reset(seed=seed)
    frames, labels = env.render_states(env.sample_states(count))
    return torch.from_numpy(frames), torch.from_numpy(labels.astype(np.int64))


def frame_source(env_name: str, budget: Budget) -> Callable[[int, int], tuple[torch.Tensor, torch.Tensor]]:
    """``(seed, count) -> (frames, labels)`` of environment ``env_name`` at ``budget``'s sizes."""
    if env_name in ("chemical-pixels", "chemical-pixels-two-tone"):
        env = ChemicalPixelsEnv(graph="chain", num_objects=budget.num_objects, frame_size=budget.frame_size,
                                two_tone=env_name.endswith("two-tone"))
        return lambda seed, count: frames_of(env, seed, count)
    if env_name == "sprites":
        if budget.num_objects < 2:
            raise ValueError("sprites needs --num-objects >= 2 (the agent and at least one fish)")
        sprites = SpritesEnv(num_fish=budget.num_objects - 1, frame_size=budget.frame_size)

        def recorded(seed: int, count: int) -> tuple[torch.Tensor, torch.Tensor]:
            frames, labels = record_frames(sprites, seed, count)
            return torch.from_numpy(frames), torch.from_numpy(labels.astype(np.int64))
        return recorded
    raise ValueError(f"unknown env {env_name!r}; one of {ENVS}")


def score(model: SlotModel, frames: torch.Tensor, labels: torch.Tensor, with_masks: bool) -> tuple[float, float]:
    """Mean FG-ARI over the frames, the masks given to slot attention or not, and the slot identity:
    the share of foreground pixels in the slot the mask prior binds their object to (slot ``1 + j``
    for object ``j``; FG-ARI is blind to which slot holds which object, a slot-wise factor is not)."""
    model.eval()
    scores, identity = [], []
    for start in range(0, len(frames), 128):
        f, lab = frames[start : start + 128], labels[start : start + 128]
        allowed = token_masks(lab, model.config.num_slots, rule=model.config.token_mask) if with_masks else None
        if allowed is not None and model.config.mask_assignment == "matched":
            allowed = model.match_segments(f, allowed)
        segments = model.segment(f, allowed)
        scores.append(fg_ari(lab.numpy(), segments.numpy()))
        identity.append((segments == lab)[lab > 0].float().numpy())
    return float(np.nanmean(np.concatenate(scores))), float(np.concatenate(identity).mean())


def train_variant(variant: str, seed: int, budget: Budget, autoencoder_state: dict[str, Any],
                  train: tuple[torch.Tensor, torch.Tensor], token_mask: str = "touch",
                  mask_assignment: str = "index", mask_binding: float = 0.0) -> tuple[SlotModel, dict[str, Any]]:
    """Slot attention and decoder trained with mask prior ``variant`` (masks per token by ``token_mask``,
    :func:`causal.slots.token_masks`; ``mask_binding``: ``SlotConfig.mask_binding``); the model and its
    training record."""
    torch.manual_seed(seed)
    config = SlotConfig(num_slots=budget.slots, mask_prior=variant, token_mask=token_mask,
                        mask_assignment=mask_assignment, mask_binding=mask_binding)
    model = SlotModel(config, budget.frame_size)
    model.autoencoder.load_state_dict(autoencoder_state)
    model.autoencoder.requires_grad_(False)
    trainer = SlotTrainer(model, budget.slot_updates, seed=seed)
    batches = torch.Generator().manual_seed(seed)
    started, losses = time.perf_counter(), {}
    for u in range(1, budget.slot_updates + 1):
        idx = torch.randint(len(train[0]), (config.batch_size,), generator=batches)
        losses = trainer.update(train[0][idx], train[1][idx])
        if u % budget.log_every == 0:
            print(f"  seed {seed} {variant}: update {u} {losses}", file=sys.stderr, flush=True)
    return model, {"train_seconds": time.perf_counter() - started, "final_losses": losses}


def run_seed(seed: int, budget: Budget, save: Callable[[dict[str, Any]], None] = lambda _: None,
             env: str = "chemical-pixels", token_mask: str = "touch", mask_assignment: str = "index",
             variants: tuple[str, ...] = VARIANTS, mask_binding: float = 0.0) -> dict[str, Any]:
    """Every variant for one seed: FG-ARI without (and for the oracle with) masks on unseen frames of
    ``env``; ``save`` gets the seed's record after each variant."""
    torch.manual_seed(seed)
    source = frame_source(env, budget)
    train = source(seed, budget.train_frames)
    test = source(seed + EVAL_SEED_OFFSET, budget.eval_frames)
    base = SlotModel(SlotConfig(num_slots=budget.slots), budget.frame_size)
    started = time.perf_counter()
    ae_loss = fit_autoencoder(base.autoencoder, train[0], budget.ae_updates, seed=seed)
    out: dict[str, Any] = {"seed": seed, "env": env, "token_mask": token_mask, "mask_assignment": mask_assignment,
                           "mask_binding": mask_binding, "num_slots": budget.slots,
                           "autoencoder": {"final_mse": ae_loss, "seconds": time.perf_counter() - started}}
    for variant in variants:
        model, record = train_variant(variant, seed, budget, base.autoencoder.state_dict(), train, token_mask,
                                      mask_assignment, mask_binding)
        fg, identity = score(model, *test, with_masks=False)
        record["slots"], record["slot_identity"] = {"fg_ari": fg}, identity
        if variant == "always":
            record["fg_ari_with_masks"] = score(model, *test, with_masks=True)[0]
        out[variant] = record
        print(f"seed {seed} {variant}: {record}", file=sys.stderr, flush=True)
        save(out)
    return out


def table(results: list[dict[str, Any]]) -> str:
    """Markdown: FG-ARI per variant, mean and standard deviation over seeds."""
    def cell(values: list[float]) -> str:
        return f"{np.mean(values):.2f} +- {np.std(values):.2f}" if len(values) > 1 else f"{values[0]:.2f}"
    rows = ["| mask prior | FG-ARI, no masks at inference | FG-ARI, masks at inference | slot identity, no masks "
            "| train s (mean) |", "|---|---|---|---|---|"]
    for variant in (v for v in VARIANTS if all(v in r for r in results)):
        no_masks = [r[variant]["slots"]["fg_ari"] for r in results]
        with_masks = [r[variant]["fg_ari_with_masks"] for r in results if "fg_ari_with_masks" in r[variant]]
        identity = [r[variant]["slot_identity"] for r in results]
        seconds = np.mean([r[variant]["train_seconds"] for r in results])
        rows.append(f"| {variant} | {cell(no_masks)} | {cell(with_masks) if with_masks else '-'} | {cell(identity)} "
                    f"| {seconds:.0f} |")
    return "\n".join(rows)


def _weight(text: str) -> float:
    """A loss weight from the command line: a float >= 0, refused before anything runs."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a weight is a number, got {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"a weight must be >= 0, got {text!r}")
    return value


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", choices=ENVS, default="chemical-pixels", help="the rendered environment")
    p.add_argument("--token-mask", choices=TOKEN_MASKS, default="touch",
                   help="which slots a token may take under the masks (causal.slots.token_masks)")
    p.add_argument("--mask-assignment", choices=MASK_ASSIGNMENTS, default="index",
                   help="which slot gets which segment under the masks (SlotConfig.mask_assignment)")
    p.add_argument("--mask-binding", type=_weight, default=0.0,
                   help="weight of the masks' binding term (SlotConfig.mask_binding; 0: the masks only restrict "
                        "the attention)")
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS), help="the mask priors to train")


def main(argv: list[str] | None = None) -> None:
    table_main(argv, description=__doc__, budget_type=Budget, default_out=Path("benchmark-results/slots/table.json"),
               run_seed=lambda seed, budget, args, save: run_seed(seed, budget, save, args.env, args.token_mask,
                                                                  args.mask_assignment, tuple(args.variants),
                                                                  args.mask_binding),
               table=table,
               add_arguments=_add_arguments)


if __name__ == "__main__":
    main()
