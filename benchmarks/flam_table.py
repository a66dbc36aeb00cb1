"""FLAM's Tables 8.1 and 8.2 analogues on MultiGrid agents (chapter 8): 10-step prediction PSNR of
FLAM, the monolithic latent action model of equal latent capacity, the two-stage slot baseline
(``--models two-stage``) and the FSQ autoencoder's reconstruction ceiling, on unseen seeds; DCI of
the latent actions against the agents' true actions, and Table 8.2's own reading: DCI of the factors
against the agents' positions.

    python -m benchmarks.flam_table --seed 0

Action-free videos of a uniformly random policy; the autoencoder is trained first and frozen
(eq. 8.1), then each latent action model on short clips of its features (eq. 8.6). Prediction: the
chapter's protocol (latent actions inferred from the unseen true frames, predictions fed back).
DCI, by linear probes (causal/dci.py), D and C over factors (a factor's dimensions grouped), in two
readings. ``dci_*``: the posterior means of the latent actions of each factor (FLAM: a slot;
monolithic: a block of ``d_a`` channels of its one latent) against the 4 agents' actions.
``dci_*_positions``: the chapter's Table 8.2 ("each factor as a latent variable ... how well it encodes
each agent's information ... position prediction accuracy"): each slot's state xi_t against every
agent's cell (x and y probes, summed per agent), FLAM and the two-stage baseline only (the monolithic
model has no factor states). Table 8.5-8.6's ablations of FLAM: ``--no-temporal-attention`` (SAVi-style
slots) and ``--coupling global`` (Global-Coupled FLAM). ``dci_*_positions_latent``: the latent actions (FLAM per slot,
monolithic in K chunks of ``d_a``: the equal-capacity comparison) against the positions at t+1 they
were inferred with. ``random``: Gaussian codes of the same shapes (chance). ``observed moves``: each
agent's observed move as its code (``envs.multigrid_agents.displacement_codes``), the ceiling of
the latent actions against the actions (a blocked move looks like a stay).
One torch thread. Budget: results.md's run (1,200 updates per model) took 4.5 min per autoencoder,
13 min of FLAM training and 15 of monolithic training, about 22 minutes of wall time with the models
in parallel processes on a loaded 2-core machine (load average 12-15); under 30 minutes either way.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from causal.dci import DCI, dci, position_dci
from causal.flam import (
    FLAM, MASK_PRIORS, FLAMConfig, LAMTrainer, MonolithicLAM, encode_clips, fit_autoencoder, psnr, rollout,
)
from causal.flam_learner import observed_move_dci
from causal.flam_nets import FSQAutoencoder
from causal.slots import frames_to_tensor
from envs.multigrid_agents import MultiGridAgentsEnv, record_videos


@dataclass(frozen=True)
class Args:
    seed: int
    episodes: int
    episode_steps: int
    eval_episodes: int
    horizon: int
    clip: int
    ae_updates: int
    updates: int
    slot_dim: int
    action_dim: int
    beta_kl: float
    variant: str
    models: tuple[str, ...]
    lr: float
    lr_decay: str
    lr_final: float
    num_slots: int
    mask_prior: str
    aggregator: str
    no_temporal_attention: bool
    coupling: str
    static_background: bool
    slot_reconstruction: float
    mask_binding: float
    slot_stage_updates: int
    action_levels: tuple[int, ...]
    out: str


def parse_args(argv: list[str] | None = None) -> Args:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=200, help="training videos")
    p.add_argument("--episode-steps", type=int, default=20, help="steps per training video")
    p.add_argument("--eval-episodes", type=int, default=100, help="unseen videos for PSNR and DCI")
    p.add_argument("--horizon", type=int, default=10, help="prediction steps")
    p.add_argument("--clip", type=int, default=4, help="frames per training clip")
    p.add_argument("--ae-updates", type=int, default=300, help="FSQ autoencoder updates (eq. 8.1)")
    p.add_argument("--updates", type=int, default=1000, help="updates of each latent action model")
    p.add_argument("--slot-dim", type=int, default=32)
    p.add_argument("--action-dim", type=int, default=8, help="d_a per slot; the monolithic latent is K * d_a")
    p.add_argument("--beta-kl", type=float, default=1e-3)
    p.add_argument("--variant", choices=("independent", "correlated"), default="independent",
                   help="correlated: agent 1 repeats agent 0 (section 8.3), FLAM alone with K = 3")
    p.add_argument("--models", nargs="+", choices=("flam", "monolithic", "two-stage"), default=["flam", "monolithic"],
                   help="two-stage: the slot baseline of Table 8.1 (slots learned first, frozen, then per-slot latent actions)")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--lr-decay", choices=("constant", "cosine"), default="constant",
                   help="cosine: the learning rate decays to --lr-final over --updates (not in the chapter)")
    p.add_argument("--lr-final", type=float, default=1e-4)
    p.add_argument("--num-slots", type=int, default=0,
                   help="K (0: one per independently acting agent plus one for the background)")
    p.add_argument("--aggregator", choices=("cross-attention", "broadcast"), default="cross-attention")
    p.add_argument("--no-temporal-attention", action="store_true",
                   help="Table 8.5's ablation: SAVi-style slots, no temporal attention in the factorizer")
    p.add_argument("--coupling", choices=("per-slot", "global"), default="per-slot",
                   help="global: Table 8.5's Global-Coupled FLAM")
    p.add_argument("--mask-prior", choices=MASK_PRIORS, default="none",
                   help="FLAM: Dyn-O's annealed mask prior from the renderer's masks in training (never at "
                        "evaluation); foreground: the same, annealed, saying only which tokens are agents")
    p.add_argument("--static-background", action="store_true",
                   help="FLAM: slot 0 (the background's) gets no latent action (FLAMConfig.static_background)")
    p.add_argument("--slot-reconstruction", type=float, default=0.0,
                   help="FLAM: weight of an added reconstruction of e_t from its slots (0: eq. 8.6 alone)")
    p.add_argument("--mask-binding", type=float, default=0.0,
                   help="FLAM with a mask prior: weight of the term that teaches the slot attention without the "
                        "masks to bind as the masks do (FLAMConfig.mask_binding; 0: the prior only restricts)")
    p.add_argument("--slot-stage-updates", type=int, default=600,
                   help="two-stage: updates of its first stage (slots by reconstruction, with --mask-prior)")
    p.add_argument("--action-levels", type=int, nargs="+", default=[],
                   help="FSQ levels of each slot's latent action (sets d_a to their count; FLAM only, no KL): "
                        "a hard bottleneck instead of the Gaussian")
    p.add_argument("--out", default="", help="write the results as JSON here")
    args = vars(p.parse_args(argv))
    if args["action_levels"]:
        if set(args["models"]) - {"flam", "two-stage"}:
            p.error("--action-levels quantises FLAM's latent actions: use it with --models flam or two-stage")
        if any(level < 3 or level % 2 == 0 for level in args["action_levels"]):
            p.error(f"--action-levels must be odd and >= 3 (FSQ), got {args['action_levels']}")
        args["action_dim"] = len(args["action_levels"])
    if args["num_slots"] == 1 or args["num_slots"] < 0:
        p.error(f"--num-slots must be 0 (agents + 1) or >= 2 (the background's slot and at least one more), got {args['num_slots']}")
    if args["mask_binding"] < 0 or (args["mask_binding"] > 0 and args["mask_prior"] == "none"):
        p.error(f"--mask-binding must be >= 0 and needs a --mask-prior, got {args['mask_binding']} with "
                f"--mask-prior {args['mask_prior']}")
    if args["variant"] == "correlated" and args["mask_prior"] == "annealed":
        p.error("--mask-prior annealed points slots at agents in index order, which on the correlated variant is "
                "the grouping under test: use --mask-prior foreground or none")
    return Args(**{**args, "models": tuple(args["models"]), "action_levels": tuple(args["action_levels"])})


def sample_clips(features: torch.Tensor, labels: torch.Tensor, generator: torch.Generator, batch: int,
                 clip: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``batch`` random clips of ``clip`` frames of the features ``[E, T, n, d_e]`` and their token labels."""
    episodes, steps = features.shape[:2]
    e = torch.randint(episodes, (batch,), generator=generator)
    t = torch.randint(steps - clip + 1, (batch,), generator=generator)
    frames = t[:, None] + torch.arange(clip)
    return features[e[:, None], frames], labels[e[:, None], frames]


def train_lam(model: nn.Module, features: torch.Tensor, labels: torch.Tensor, args: Args, log: str,
              prior: str | None = None) -> float:
    """Train on random clips of ``args.clip`` frames of the training features (token labels
    ``[E, T, n]`` for the mask prior: FLAM's ``args.mask_prior`` unless ``prior`` says); seconds taken."""
    prior = prior or (args.mask_prior if isinstance(model, FLAM) else "none")
    trainer, start = LAMTrainer(model, seed=args.seed, mask_prior=prior, total_updates=args.updates), time.time()
    generator = torch.Generator().manual_seed(args.seed)
    for update in range(args.updates):
        terms = trainer.update(*sample_clips(features, labels, generator, model.config.batch_size, args.clip))
        if update % 200 == 0 or update == args.updates - 1:
            print(f"  {log} update {update}: {json.dumps({k: round(v, 5) for k, v in terms.items()})}", flush=True)
    return time.time() - start


def train_two_stage(model: FLAM, features: torch.Tensor, labels: torch.Tensor, args: Args) -> float:
    """Table 8.1's two-stage slot baseline (PlaySlot-like): first the factorizer and a slot decoder learn
    slots by reconstructing each frame's features from them (Dyn-O's feature term, the same mask prior
    as FLAM's over ``args.slot_stage_updates``), then both are frozen and the per-slot IDM, FDM and
    aggregator learn eq. 8.6 on the frozen slots for ``args.updates``; seconds taken."""
    masks, start = LAMTrainer(model, seed=args.seed, mask_prior=args.mask_prior,
                              total_updates=args.slot_stage_updates), time.time()
    optimizer = torch.optim.Adam([*model.factorizer.parameters(), *model.slot_decoder.parameters()], lr=args.lr)
    generator = torch.Generator().manual_seed(args.seed + 1)
    for update in range(args.slot_stage_updates):
        clips, clip_labels = sample_clips(features, labels, generator, model.config.batch_size, args.clip)
        slots, _ = model.factorizer(clips, masks.masks_for(clip_labels))
        loss = (model.slot_decoder(slots.flatten(0, 1))[0].view_as(clips) - clips).pow(2).flatten(2).sum(-1).mean()
        optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        masks.updates += 1
        if update % 200 == 0 or update == args.slot_stage_updates - 1:
            print(f"  two-stage slots update {update}: slot_reconstruction_sse {float(loss.detach()):.5f}", flush=True)
    model.factorizer.requires_grad_(False)
    model.slot_decoder.requires_grad_(False)
    return time.time() - start + train_lam(model, features, labels, args, "two-stage", prior="none")


def dci_keys(scores: DCI, suffix: str = "") -> dict[str, float]:
    return {f"dci_d{suffix}": scores.disentanglement, f"dci_c{suffix}": scores.completeness,
            f"dci_i{suffix}": scores.informativeness}


def evaluate(model: nn.Module, autoencoder: FSQAutoencoder, features: torch.Tensor, frames: torch.Tensor,
             actions: torch.Tensor, positions: torch.Tensor, num_slots: int, grid_size: int) -> dict[str, float]:
    """10-step PSNR (mean over clips); DCI of the latent actions' posterior means against the actions
    (``dci_*``) and against the positions at t+1 (``dci_*_positions_latent``); for slot models, DCI of
    the slots' states against the positions (``dci_*_positions``, Table 8.2's reading)."""
    model.eval()
    grid = frames.shape[2] // 4
    with torch.no_grad():
        predicted = rollout(model, features, autoencoder.fsq)
        images = autoencoder.decode(predicted.flatten(0, 1), grid).view(frames.shape[0], -1, 3, *frames.shape[2:4])
        target = frames_to_tensor(frames[:, 1:].flatten(0, 1)).view_as(images)
        codes = model.infer(features).flatten(0, 1)
        states = model.factorizer(features)[0].flatten(0, 1) if isinstance(model, FLAM) else None
    codes = codes.reshape(len(codes), num_slots, -1)
    results = {"psnr": float(psnr(images, target).mean()), **dci_keys(dci(codes, actions.flatten(0, 1), classes=5)),
               **dci_keys(position_dci(codes, positions[:, 1:].flatten(0, 1), grid_size), "_positions_latent")}
    if states is not None:
        scores = position_dci(states, positions.flatten(0, 1), grid_size)
        share = scores.importance / scores.importance.sum(0, keepdim=True).clamp_min(1e-12)
        results.update({**dci_keys(scores, "_positions"),
                        "positions_importance": [[round(float(v), 3) for v in row] for row in share.T]})
    return results


def matched_dci(model: FLAM, features: torch.Tensor, actions: torch.Tensor, positions: torch.Tensor,
                slots: torch.Tensor, grid_size: int) -> dict[str, float]:
    """A diagnostic, not the chapter's metric: DCI with factor ``i`` = the slot holding agent ``i`` in
    each frame (``slots`` int ``[E, T+1, N]`` from :func:`agent_slots`, i.e. from the true masks):
    what D, C and I would be if every agent kept one slot across videos. Latent actions against the
    actions (``dci_*_matched``), slots' states against the positions (``dci_*_positions_matched``)."""
    with torch.no_grad():
        states = model.factorizer(features)[0]
        codes = model.infer(features)
    return {**dci_keys(dci(per_agent(codes, slots[:, :-1]), actions.flatten(0, 1), classes=5), "_matched"),
            **dci_keys(position_dci(per_agent(states, slots), positions.flatten(0, 1), grid_size), "_positions_matched")}


def per_agent(values: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """``[E * T, N, d]``: per frame, agent ``i``'s slot's values (``values [E, T, K, d]``, ``slots`` int ``[E, T, N]``)."""
    return values.gather(2, slots[..., None].expand(-1, -1, -1, values.shape[-1])).flatten(0, 1)


def random_codes(actions: torch.Tensor, positions: torch.Tensor, config: FLAMConfig, grid_size: int,
                 seed: int) -> dict[str, float]:
    """Table 8.2's Random row: Gaussian codes shaped as FLAM's latent actions (against the actions)
    and as its slots (against the positions)."""
    generator = torch.Generator().manual_seed(seed)
    transitions, frames = actions.flatten(0, 1), positions.flatten(0, 1)
    latent = torch.randn(len(transitions), config.num_slots, config.action_dim, generator=generator)
    states = torch.randn(len(frames), config.num_slots, config.slot_dim, generator=generator)
    return {**dci_keys(dci(latent, transitions, classes=5)),
            **dci_keys(position_dci(states, frames, grid_size), "_positions")}


def token_labels(labels: np.ndarray, num_slots: int = 0, num_agents: int = 0) -> torch.Tensor:
    """Each feature token's segment ``[E, T, n]`` (0 background, ``1 + i`` agent ``i``; one 4x4 token per
    cell), the segment the mask prior points slot ``k`` at. With fewer agent slots than agents
    (``num_slots - 1 < num_agents``: Table 8.3's K = 2) agents share slots in index order: agent ``i``
    to slot ``1 + i * (num_slots - 1) // num_agents`` (K = 2 + 1 of 4 agents: 0 and 1 in slot 1, 2 and
    3 in slot 2). Not for the correlated variant: there this grouping is the true one."""
    tokens = torch.from_numpy(labels[:, :, ::4, ::4].reshape(labels.shape[0], labels.shape[1], -1).copy())
    if 0 < num_slots - 1 < num_agents:
        agent = tokens.long() - 1
        tokens = torch.where(tokens > 0, 1 + agent * (num_slots - 1) // num_agents, 0).to(tokens.dtype)
    return tokens


def agent_slots(attention: torch.Tensor, labels: torch.Tensor, num_agents: int) -> torch.Tensor:
    """int ``[B, T, N]``: the slot holding most of agent ``i``'s attention in each frame (labels
    ``[B, T, H, W]`` at one 4x4 token per grid cell)."""
    tokens = labels[:, :, ::4, ::4].flatten(2).long()
    owned = torch.stack([(tokens == 1 + i).float() for i in range(num_agents)], dim=2)
    return torch.einsum("btkn,btin->btik", attention, owned).argmax(-1)


def agent_slot_share(slots: torch.Tensor, num_slots: int) -> list[list[float]]:
    """``[N][K]``: the share of frames in which slot ``k`` holds agent ``i`` (:func:`agent_slots`); one
    slot per agent across videos is what lets a probe find an agent in the same factor every time."""
    counts = torch.nn.functional.one_hot(slots.flatten(0, 1), num_slots).float().mean(0)
    return [[round(float(v), 3) for v in row] for row in counts]


def slot_sharing(slots: torch.Tensor) -> dict[str, float]:
    """Shares of frames where agents 0 and 1 share a slot, and where every other agent has its own."""
    same = slots[..., 0] == slots[..., 1]
    others = slots[..., [0] + list(range(2, slots.shape[-1]))]
    distinct = torch.stack([(others[..., i] != others[..., j]) for i in range(others.shape[-1])
                            for j in range(i + 1, others.shape[-1])], -1).all(-1)
    all_distinct = torch.stack([(slots[..., i] != slots[..., j]) for i in range(slots.shape[-1])
                                for j in range(i + 1, slots.shape[-1])], -1).all(-1)
    return {"agents_0_1_share_slot": float(same.float().mean()),
            "grouped_as_actions": float((same & distinct).float().mean()),
            "every_agent_own_slot": float(all_distinct.float().mean())}


def code_overlap(features: torch.Tensor, labels: torch.Tensor, segments: int) -> list[list[float]]:
    """``[S][S]``: how alike the frozen autoencoder's codes of two segments are, the overlap
    ``sum_c min(p_a(c), p_b(c))`` of their tokens' code histograms (1: the same codes in the same
    shares; 0: no code in common). Features ``[..., n, d_e]`` (FSQ codes), token labels ``[..., n]``.
    Two agents whose tokens share codes differ only in what the encoder put in the tokens around them,
    and slot attention, which reads a token's code, cannot tell them apart from it."""
    codes, inverse = torch.unique(features.flatten(0, -2), dim=0, return_inverse=True)
    flat = labels.flatten().long()
    histograms = torch.zeros(segments, len(codes))
    histograms.index_put_((flat, inverse), torch.ones(len(flat)), accumulate=True)
    shares = histograms / histograms.sum(1, keepdim=True).clamp_min(1.0)
    overlap = torch.minimum(shares[:, None, :], shares[None, :, :]).sum(-1)
    return [[round(float(v), 3) for v in row] for row in overlap]


def main(args: Args) -> dict[str, dict[str, float]]:
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    env = MultiGridAgentsEnv(correlated=args.variant == "correlated")
    train = record_videos(env, args.episodes, args.episode_steps, seed=args.seed * 100_000)
    test = record_videos(env, args.eval_episodes, args.horizon, seed=args.seed * 100_000 + 50_000)
    train_frames, test_frames = torch.from_numpy(train["frames"]), torch.from_numpy(test["frames"])
    num_slots = args.num_slots or (env.num_agents - 1 if env.correlated else env.num_agents) + 1
    config = FLAMConfig(num_slots=num_slots, slot_dim=args.slot_dim, action_dim=args.action_dim,
                        beta_kl=args.beta_kl, lr=args.lr, lr_final=args.lr_final,
                        lr_decay_updates=args.updates if args.lr_decay == "cosine" else 0, slot_reconstruction=args.slot_reconstruction, aggregator=args.aggregator,
                        mask_binding=args.mask_binding,
                        temporal_attention=not args.no_temporal_attention, coupling=args.coupling,
                        static_background=args.static_background, action_levels=args.action_levels)
    autoencoder = FSQAutoencoder(config.levels)
    start = time.time()
    fit_autoencoder(autoencoder, train_frames.flatten(0, 1), args.ae_updates, seed=args.seed)
    print(f"autoencoder: {time.time() - start:.0f} s", flush=True)
    train_features, test_features = encode_clips(autoencoder, train_frames), encode_clips(autoencoder, test_frames)
    grid = env.frame_size // 4
    with torch.no_grad():
        recon = autoencoder(frames_to_tensor(test_frames[:, 1:].flatten(0, 1)))
    target = frames_to_tensor(test_frames[:, 1:].flatten(0, 1))
    shape = (args.eval_episodes, args.horizon, 3, env.frame_size, env.frame_size)
    results = {"recon": {"psnr": float(psnr(recon.view(shape), target.view(shape)).mean()),
                         "code_overlap": code_overlap(test_features, token_labels(test["labels"]), env.num_agents + 1)}}
    agents = torch.tensor(results["recon"]["code_overlap"])[1:, 1:] - torch.eye(env.num_agents)
    print(f"autoencoder: largest overlap of two agents' codes {float(agents.max()):.3f} (0: none shared)", flush=True)
    copy = (train_features[:, 1:] - train_features[:, :-1]).pow(2).flatten(2).sum(-1).mean()
    print(f"copy-last-frame prediction_sse on the training videos: {float(copy):.4f}", flush=True)
    actions, positions = torch.from_numpy(test["actions"]), torch.from_numpy(test["positions"])
    models = {"flam": FLAM, "monolithic": MonolithicLAM, "two-stage": FLAM}
    labels = token_labels(train["labels"], num_slots, env.num_agents)
    for name in ("flam",) if env.correlated else args.models:
        torch.manual_seed(args.seed)
        if name == "two-stage":  # the slot decoder of its first stage; eq. 8.6 alone in its second
            model = FLAM(replace(config, slot_reconstruction=1.0), grid * grid)
            seconds = train_two_stage(model, train_features, labels, args)
        else:
            model = models[name](replace(config), grid * grid)
            seconds = train_lam(model, train_features, labels, args, name)
        results[name] = {**evaluate(model, autoencoder, test_features, test_frames, actions, positions,
                                    config.num_slots, env.grid_size),
                         "train_seconds": round(seconds, 1)}
        if isinstance(model, FLAM):
            with torch.no_grad():
                attention = model.factorizer(test_features)[1]
            slots = agent_slots(attention, torch.from_numpy(test["labels"]), env.num_agents)
            results[name].update({**slot_sharing(slots), "agent_slot_share": agent_slot_share(slots, config.num_slots),
                                  **matched_dci(model, test_features, actions, positions, slots, env.grid_size)})
        print(f"{name}: {json.dumps(results[name])}", flush=True)
    results["random"] = random_codes(actions, positions, config, env.grid_size, args.seed)
    results["observed moves"] = dci_keys(observed_move_dci(positions.numpy(), actions.numpy()))
    print_table(results, args)
    if args.out:
        Path(args.out).write_text(json.dumps({"args": vars(args), "results": results}, indent=2))
    return results


def print_table(results: dict[str, dict[str, float]], args: Args) -> None:
    print(f"\n{args.variant}: {args.horizon}-step prediction on {args.eval_episodes} unseen videos, seed {args.seed}")
    print("| model | PSNR (dB) | latent actions vs actions: D / C / I | factor states vs positions: D / C / I "
          "| latent actions vs positions: D / C / I |\n|---|---|---|---|---|")
    for name, row in results.items():
        cells = [f"{row['psnr']:.2f}" if "psnr" in row else "-"]
        for suffix in ("", "_positions", "_positions_latent"):
            keys = [f"dci_{x}{suffix}" for x in "dci"]
            cells.append(" / ".join(f"{row[k]:.2f}" for k in keys) if all(k in row for k in keys) else "-")
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(parse_args())
