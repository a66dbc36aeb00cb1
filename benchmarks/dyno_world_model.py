"""Table 7.2 analogue (chapter 7, Dyn-O): 20-step rollout PSNR and SSIM on unseen seeds, the slot
world model (eq. 7.2) against a monolithic world model of matched parameter count.

Data (``--env``): episodes under uniformly random actions, each ``context + 20`` frames.

- ``chemical-pixels`` (4 objects, 32x32; the default, with ``--context 1``). Chemical redraws every
  position i.i.d. each step, which no model can predict, so each episode keeps its first layout and
  only the colours evolve (the action sets one object's colour, its descendants in the chain are
  re-drawn from the CPT): the rollouts test the colour dynamics. Training episodes come from env seed
  ``seed``, evaluation episodes from ``seed + 10_000`` (unseen layouts and colour sequences).
- ``sprites``: the bigfish-like sprite game (``envs.sprites``; ``--num-objects`` = the agent and
  ``num_objects - 1`` fish), the chapter's Table 7.2 scene. Fish swim at constant speeds that one
  frame does not show, so both models read ``--context`` frames teacher-forced before the 20
  open-loop steps (the chapter does not say how many context frames its rollouts get). Episodes reset
  with seeds ``seed, seed + 1, ...`` (evaluation: from ``seed + 10_000``); one in which the agent is
  eaten or wins within its steps is dropped and the next seed drawn (no frame follows an end), and the
  count dropped is reported. The world models also fit the reward (eq. 7.2's reward
  term); no kept episode terminates, so the termination term is left out.

Per seed: the frame autoencoder and the annealed slot model are trained as in Table 7.1's analogue
(``benchmarks.slots_table``), then frozen; the slots of every frame are computed once and put in one
order over each episode (:func:`causal.slot_world_model.align_slots`). Then, from the same batches:

- ``slot``: :class:`~causal.slot_world_model.SlotWorldModel` on the slots, decoded by the slot decoder
  and the frozen frame decoder;
- ``monolithic``: :class:`~causal.slot_world_model.MonolithicWorldModel` on the frozen encoder's whole
  feature map (one latent per frame), decoded by the frozen frame decoder, its width chosen so its
  parameter count matches the slot model's.

Both are trained teacher-forced on eq. 7.2 and scored open loop: after the ``context`` frames (read
teacher-forced; with one, the first frame alone) under the episode's next 20 actions, each predicted
frame against the true one. Also reported: the decoder ceilings (the true step-20 latents decoded);
``copy`` (the last context frame repeated: no dynamics), and the same through each model's own
decoder (``copy_slot``, ``copy_monolithic``: what the rollout is worth once its decoder is held
fixed); the PSNR over the true objects' pixels; and each rollout's error in its model's own latent
space beside holding the last context latent. Budgets are update counts; one torch thread.

    python -m benchmarks.dyno_world_model [--env sprites --num-objects 5 --context 4] [--seeds 0] [--wm-updates 3000] [--out benchmark-results/dyno/world_model.json]
    python -m benchmarks.dyno_world_model --merge seed0.json seed1.json   # one table over runs' JSON files
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
from torch import nn

from benchmarks.slots_table import Budget as SlotsBudget
from benchmarks.slots_table import train_variant
from benchmarks.seeded_table import table_main
from causal.slot_world_model import (
    MonolithicWorldModel,
    SlotWorldModel,
    WorldModelConfig,
    align_slots,
    monolithic_width,
    parameter_count,
    psnr,
    ssim,
    summary_of,
    world_model_loss,
)
from causal.slots import SlotConfig, SlotModel, fit_autoencoder, frames_to_tensor
from envs.chemical_pixels import ChemicalPixelsEnv
from envs.sprites import SpritesEnv

EVAL_SEED_OFFSET = 10_000
ENVS = ("chemical-pixels", "sprites")


@dataclasses.dataclass(frozen=True)
class Budget:
    num_objects: int = 4
    frame_size: int = 32
    horizon: int = 20
    train_episodes: int = 300
    eval_episodes: int = 100
    ae_updates: int = 300
    slot_updates: int = 1500
    wm_updates: int = 3000
    wm_batch: int = 16
    wm_hidden: int = 64
    log_every: int = 500
    context: int = 1
    """Frames each rollout reads (teacher-forced) before its ``horizon`` open-loop steps."""

    def __post_init__(self) -> None:
        if min(self.context, self.horizon, self.train_episodes, self.eval_episodes) < 1:
            raise ValueError("--context, --horizon, --train-episodes and --eval-episodes must be >= 1")

    @property
    def steps(self) -> int:
        """Actions per episode: ``context - 1`` between the context frames, then ``horizon``."""
        return self.context - 1 + self.horizon


@dataclasses.dataclass
class Episodes:
    frames: torch.Tensor
    """uint8 ``[E, T + 1, H, W, 3]``"""
    labels: torch.Tensor
    """int ``[E, T + 1, H, W]``"""
    actions: torch.Tensor
    """long ``[E, T]``"""
    rewards: torch.Tensor | None = None
    """float ``[E, T]`` where the environment gives rewards"""
    dropped: int = 0
    """episodes drawn and dropped because they ended early (sprites)"""


def episodes_of(env: ChemicalPixelsEnv, seed: int, count: int, horizon: int) -> Episodes:
    """``count`` random-action episodes of ``horizon`` steps from ``env`` seeded ``seed``, positions
    held at each episode's first layout."""
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    states = np.empty((count, horizon + 1, 3 * env.num_objects), np.float32)
    actions = rng.integers(0, int(env.action_space.n), size=(count, horizon))
    for e in range(count):
        states[e, 0], _ = env.reset()
        for t in range(horizon):
            states[e, t + 1] = env.step(int(actions[e, t]))[0]
    positions = states[:, :1].reshape(count, 1, env.num_objects, 3)[..., 1:]
    grid = states.reshape(count, horizon + 1, env.num_objects, 3)
    grid[..., 1:] = positions
    frames, labels = env.render_states(grid.reshape(-1, 3 * env.num_objects))
    shape = (count, horizon + 1)
    return Episodes(torch.from_numpy(frames).view(*shape, *frames.shape[1:]),
                    torch.from_numpy(labels.astype(np.int64)).view(*shape, *labels.shape[1:]),
                    torch.from_numpy(actions))


def sprite_episodes(env: SpritesEnv, seed: int, count: int, steps: int) -> Episodes:
    """``count`` episodes of ``steps`` uniformly random moves (``steps + 1`` frames) of the sprite game,
    drawn from seeds ``seed, seed + 1, ...``; one that ends (the agent eaten or grown to win) within
    its steps is dropped and the next seed drawn."""
    frames = np.zeros((count, steps + 1, env.frame_size, env.frame_size, 3), np.uint8)
    labels = np.zeros((count, steps + 1, env.frame_size, env.frame_size), np.int64)
    actions = np.zeros((count, steps), np.int64)
    rewards = np.zeros((count, steps), np.float32)
    kept = drawn = 0
    while kept < count:
        if drawn >= 20 * count:
            raise RuntimeError(f"only {kept} of {drawn} sprite episodes lasted {steps} steps")
        _, info = env.reset(seed=seed + drawn)
        rng = np.random.default_rng((seed, drawn))
        drawn += 1
        frames[kept, 0], labels[kept, 0] = info["frame"], info["masks"].argmax(0)
        ended = False
        for t in range(steps):
            actions[kept, t] = rng.integers(env.num_moves)
            _, rewards[kept, t], terminated, truncated, info = env.step(int(actions[kept, t]))
            frames[kept, t + 1], labels[kept, t + 1] = info["frame"], info["masks"].argmax(0)
            if terminated or truncated:
                ended = True
                break
        if not ended:
            kept += 1
    return Episodes(torch.from_numpy(frames), torch.from_numpy(labels), torch.from_numpy(actions),
                    torch.from_numpy(rewards), dropped=drawn - count)


@torch.no_grad()
def latents_of(model: SlotModel, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Aligned slots ``[E, T + 1, K, d]`` and flattened encoder features ``[E, T + 1, n * d_e]``."""
    flat = frames.flatten(0, 1)
    slots, alpha, features = [], [], []
    for start in range(0, len(flat), 256):
        out = model(flat[start : start + 256])
        slots.append(out.slots)
        alpha.append(out.alpha)
        features.append(out.features.flatten(1))
    shape = frames.shape[:2]
    aligned, _ = align_slots(torch.cat(slots).view(*shape, *slots[0].shape[1:]),
                             torch.cat(alpha).view(*shape, *alpha[0].shape[1:]))
    return aligned, torch.cat(features).view(*shape, -1)


@torch.no_grad()
def decode_slots(model: SlotModel, slots: torch.Tensor) -> torch.Tensor:
    """Images ``[B, 3, H, W]`` of slots ``[B, K, d]`` (slot decoder, then the frozen frame decoder)."""
    features, _ = model.slot_decoder(slots)
    return model.autoencoder.decoder(features.transpose(1, 2).reshape(len(slots), -1, model.grid, model.grid))


@torch.no_grad()
def decode_features(model: SlotModel, features: torch.Tensor) -> torch.Tensor:
    """Images of flattened encoder features ``[B, n * d_e]`` (the frozen frame decoder)."""
    return model.autoencoder.decoder(features.view(len(features), model.grid * model.grid, -1)
                                     .transpose(1, 2).reshape(len(features), -1, model.grid, model.grid))


def train_world_model(wm: nn.Module, latents: torch.Tensor, actions: torch.Tensor, budget: Budget,
                      seed: int, name: str, rewards: torch.Tensor | None = None) -> dict[str, Any]:
    """Teacher-forced eq. 7.2 on random episodes: the next latents, and the rewards where given
    (Chemical has no reward; no training episode terminates, so no termination term)."""
    optimizer = torch.optim.Adam(wm.parameters(), lr=WorldModelConfig().lr)
    batches = torch.Generator().manual_seed(seed)
    started, loss = time.perf_counter(), torch.tensor(float("nan"))
    for u in range(1, budget.wm_updates + 1):
        idx = torch.randint(len(latents), (budget.wm_batch,), generator=batches)
        loss = world_model_loss(wm(latents[idx, :-1], actions[idx]), latents[idx, 1:],
                                None if rewards is None else rewards[idx])
        optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(wm.parameters(), 1.0)
        optimizer.step()
        if u % budget.log_every == 0:
            print(f"  seed {seed} {name}: update {u} loss {float(loss.detach()):.5f}", file=sys.stderr, flush=True)
    return {"parameters": parameter_count(wm), "final_loss": float(loss.detach()),
            "train_seconds": time.perf_counter() - started}


def object_psnr(images: torch.Tensor, truth: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """PSNR in dB per image ``[..., 3, h, w]`` over the pixels the true label maps ``[..., h, w]`` give
    to an object (label > 0), NaN where a frame shows none. Full-frame PSNR on a textured background
    is mostly the background's; this is the objects' share, what the dynamics has to move."""
    on = (labels > 0).unsqueeze(-3).to(images.dtype)
    squared = ((images.clamp(0, 1) - truth).square() * on).flatten(-3).sum(-1)
    count = on.flatten(-3).sum(-1) * images.shape[-3]
    mse = (squared / count).clamp_min(1e-10)
    return torch.where(count > 0, 10.0 * torch.log10(1.0 / mse), torch.full_like(mse, float("nan")))


def scores(images: torch.Tensor, truth: torch.Tensor, labels: torch.Tensor | None = None) -> dict[str, Any]:
    """PSNR and SSIM of predicted frames ``[E, H, 3, h, w]`` against the true ``[E, H, 3, h, w]``: at
    the last step (mean and standard error over episodes) and averaged over every step; with the true
    label maps ``[E, H, h, w]``, also the PSNR over the objects' pixels (:func:`object_psnr`)."""
    p = psnr(images, truth)
    s = torch.stack([ssim(images[:, t], truth[:, t]) for t in range(images.shape[1])], 1)
    out = {"psnr_last": summary_of(p[:, -1].tolist()), "ssim_last": summary_of(s[:, -1].tolist()),
           "psnr_per_step": p.mean(0).tolist(), "ssim_per_step": s.mean(0).tolist()}
    if labels is not None:
        o = object_psnr(images, truth, labels)
        last = o[:, -1][~o[:, -1].isnan()]
        out["psnr_objects_last"] = summary_of(last.tolist())
        out["psnr_objects_per_step"] = o.nanmean(0).tolist()
    return out


def evaluate(model: SlotModel, slot_wm: SlotWorldModel, mono_wm: MonolithicWorldModel,
             test: Episodes, context: int = 1) -> dict[str, Any]:
    """Open-loop rollouts after ``context`` frames (the first ``context - 1`` transitions read
    teacher-forced), every later frame predicted and scored."""
    c = context - 1
    slots, features = latents_of(model, test.frames)
    truth = frames_to_tensor(test.frames[:, context:].flatten(0, 1)).view(*test.frames.shape[:1], -1, 3,
                                                                            *test.frames.shape[2:4])
    e, h = truth.shape[:2]
    ahead = test.actions[:, c:]
    slot_hidden = slot_wm.observe(slots[:, :c], test.actions[:, :c]) if c else None
    mono_hidden = mono_wm.observe(features[:, :c], test.actions[:, :c]) if c else None
    slot_rolled = slot_wm.rollout(slots[:, c], ahead, slot_hidden)
    mono_rolled = mono_wm.rollout(features[:, c], ahead, mono_hidden)
    slot_images = decode_slots(model, slot_rolled.flatten(0, 1)).view_as(truth)
    mono_images = decode_features(model, mono_rolled.flatten(0, 1)).view_as(truth)
    copy = frames_to_tensor(test.frames[:, c])[:, None].expand_as(truth)
    copy_slot = decode_slots(model, slots[:, c])[:, None].expand_as(truth)
    copy_features = decode_features(model, features[:, c])[:, None].expand_as(truth)
    labels, last = test.labels[:, context:], truth[:, -1:]

    def latent_error(rolled: torch.Tensor, true: torch.Tensor) -> dict[str, list[float]]:
        """Mean squared error per step in the model's own latent space, the rollout's and the copy's
        (the last context latent held): decoder-free evidence of whether the dynamics was learned."""
        future = true[:, context:]
        held = true[:, c : c + 1].expand_as(future)
        per_step = lambda x: (x - future).square().flatten(2).mean(-1).mean(0).tolist()  # noqa: E731
        return {"rollout": per_step(rolled), "copy": per_step(held)}

    return {"latent_error": {"slot": latent_error(slot_rolled, slots), "monolithic": latent_error(mono_rolled, features)},
            "slot": scores(slot_images, truth, labels), "monolithic": scores(mono_images, truth, labels),
            "copy": scores(copy, truth, labels),
            "copy_slot": scores(copy_slot, truth, labels), "copy_monolithic": scores(copy_features, truth, labels),
            "ceiling_slot": scores(decode_slots(model, slots[:, -1]).view(e, 1, *truth.shape[2:]), last, labels[:, -1:]),
            "ceiling_monolithic": scores(decode_features(model, features[:, -1]).view(e, 1, *truth.shape[2:]), last,
                                         labels[:, -1:])}


def run_seed(seed: int, budget: Budget, env_name: str = "chemical-pixels") -> dict[str, Any]:
    torch.manual_seed(seed)
    env: ChemicalPixelsEnv | SpritesEnv
    if env_name == "sprites":
        if budget.num_objects < 2:
            raise ValueError("sprites needs --num-objects >= 2 (the agent and at least one fish)")
        env = SpritesEnv(num_fish=budget.num_objects - 1, frame_size=budget.frame_size)
        train = sprite_episodes(env, seed, budget.train_episodes, budget.steps)
        test = sprite_episodes(env, seed + EVAL_SEED_OFFSET, budget.eval_episodes, budget.steps)
    elif env_name == "chemical-pixels":
        env = ChemicalPixelsEnv(graph="chain", num_objects=budget.num_objects, frame_size=budget.frame_size)
        train = episodes_of(env, seed, budget.train_episodes, budget.steps)
        test = episodes_of(env, seed + EVAL_SEED_OFFSET, budget.eval_episodes, budget.steps)
    else:
        raise ValueError(f"unknown env {env_name!r}; one of {ENVS}")
    frames = (train.frames.flatten(0, 1), train.labels.flatten(0, 1))
    base = SlotModel(SlotConfig(num_slots=budget.num_objects + 1), budget.frame_size)
    ae_loss = fit_autoencoder(base.autoencoder, frames[0], budget.ae_updates, seed=seed)
    slots_budget = SlotsBudget(num_objects=budget.num_objects, frame_size=budget.frame_size,
                               slot_updates=budget.slot_updates, log_every=budget.log_every)
    model, slot_record = train_variant("annealed", seed, slots_budget, base.autoencoder.state_dict(), frames)
    model.eval()
    slots, features = latents_of(model, train.frames)
    torch.manual_seed(seed)
    slot_wm = SlotWorldModel(slots.shape[-1], int(env.action_space.n), WorldModelConfig(hidden=budget.wm_hidden))
    width = monolithic_width(features.shape[-1], int(env.action_space.n), parameter_count(slot_wm))
    mono_wm = MonolithicWorldModel(features.shape[-1], int(env.action_space.n), width)
    out: dict[str, Any] = {"seed": seed, "env": env_name, "context": budget.context, "autoencoder_mse": ae_loss,
                           "episodes_dropped": {"train": train.dropped, "eval": test.dropped},
                           "slot_model": slot_record,
                           "slot_wm": train_world_model(slot_wm, slots, train.actions, budget, seed, "slot",
                                                        train.rewards),
                           "monolithic_wm": {"width": width, **train_world_model(mono_wm, features, train.actions,
                                                                                  budget, seed, "monolithic",
                                                                                  train.rewards)}}
    out["rollouts"] = evaluate(model, slot_wm.eval(), mono_wm.eval(), test, budget.context)
    return out


ROWS = ("slot", "monolithic", "copy", "copy_slot", "copy_monolithic", "ceiling_slot", "ceiling_monolithic")
"""The table's rows: the two world models, the copies of the last context frame (as a frame, and
through each model's decoder: no dynamics), and the decoder ceilings (the true last latents decoded)."""


def table(results: list[dict[str, Any]]) -> str:
    rows = ["| model | parameters | PSNR at step 20 | SSIM at step 20 | PSNR, mean of steps 1-20 "
            "| objects' PSNR at step 20 |", "|---|---|---|---|---|---|"]
    for name in ROWS:
        for r in results:
            if name not in r["rollouts"]:  # records written before the row existed
                continue
            s = r["rollouts"][name]
            params = {"slot": r["slot_wm"]["parameters"], "monolithic": r["monolithic_wm"]["parameters"]}.get(name, "-")
            objects = (f"{s['psnr_objects_last']['mean']:.2f} +- {s['psnr_objects_last']['stderr']:.2f}"
                       if "psnr_objects_last" in s else "-")
            rows.append(f"| {name} (seed {r['seed']}) | {params} | {s['psnr_last']['mean']:.2f} +- "
                        f"{s['psnr_last']['stderr']:.2f} | {s['ssim_last']['mean']:.3f} +- {s['ssim_last']['stderr']:.3f} "
                        f"| {np.mean(s['psnr_per_step']):.2f} | {objects} |")
    rows += ["", "| world model | latent error at steps 1 / 10 / 20, rollout / copy of the last context latent |",
             "|---|---|"]
    for name in ("slot", "monolithic"):
        for r in results:
            if "latent_error" not in r["rollouts"]:
                continue
            e = r["rollouts"]["latent_error"][name]
            cells = " / ".join(f"{e['rollout'][t]:.4f} / {e['copy'][t]:.4f}" for t in (0, 9, len(e["copy"]) - 1))
            rows.append(f"| {name} (seed {r['seed']}) | {cells} |")
    if len(results) > 1:
        rows += ["", f"| over {len(results)} seeds (mean +- sd) | PSNR at step 20 | SSIM at step 20 | objects' PSNR at step 20 "
                 "| latent error at step 20, rollout / copy |", "|---|---|---|---|---|"]
        for name in ROWS:
            if not all(name in r["rollouts"] for r in results):
                continue
            cells = [_spread([r["rollouts"][name][key]["mean"] for r in results], digits)
                     if all(key in r["rollouts"][name] for r in results) else "-"
                     for key, digits in (("psnr_last", 2), ("ssim_last", 3), ("psnr_objects_last", 2))]
            ratio = "-"
            if name in ("slot", "monolithic") and all("latent_error" in r["rollouts"] for r in results):
                ratio = _spread([r["rollouts"]["latent_error"][name]["rollout"][-1]
                                 / r["rollouts"]["latent_error"][name]["copy"][-1] for r in results], 2)
            rows.append(f"| {name} | {' | '.join(cells)} | {ratio} |")
    return "\n".join(rows)


def _spread(values: list[float], digits: int) -> str:
    return f"{np.mean(values):.{digits}f} +- {np.std(values):.{digits}f}"


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", choices=ENVS, default="chemical-pixels", help="the rendered environment")


def main(argv: list[str] | None = None) -> None:
    table_main(argv, description=__doc__, budget_type=Budget, default_out=Path("benchmark-results/dyno/world_model.json"),
               run_seed=lambda seed, budget, args, _save: run_seed(seed, budget, args.env), table=table,
               add_arguments=_add_arguments)


if __name__ == "__main__":
    main()
