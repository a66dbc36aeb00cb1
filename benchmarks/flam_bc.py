"""FLAM's Table 8.4 analogue: behaviour cloning from pseudo-labels (eq. 8.7).

    python -m benchmarks.flam_bc --env multigrid --seed 0 --ae-updates 3000 --updates 12000 --beta-kl 3e-2 --mask-binding 1
    python -m benchmarks.flam_bc --env sprites --seed 0

The chapter's protocol (it uses Procgen's Bigfish and Starpilot with a PPG expert and 1M frames) on
one of two games of ours (``--env``):

- ``multigrid``: :class:`envs.multigrid_agents.MultiGridGoalEnv`, the player (agent 0) collects goals
  while ``--num-agents`` - 1 other agents wander at random; the expert
  (:func:`envs.multigrid_agents.goal_expert_action`) walks to the goal. A move is a whole cell (4
  pixels), and the frames are FLAM's MultiGrid frames, on which its latent actions read the agents'
  moves (the Table 8.2 benchmark);
- ``sprites``: the bigfish-like game of envs/sprites.py with its look-ahead expert
  (:func:`envs.sprites.expert_action`); the agent moves 1.3 pixels a step, on textured backgrounds.

A demonstration dataset of the expert (a random move with probability ``--epsilon``), of which a
small subset keeps its action labels (``--labels``, 1k and 10k by default, of ``--transitions``).
FLAM is trained on the whole dataset's frames without actions (the FSQ autoencoder first, then
eq. 8.6 on clips, the annealed mask prior of the exact masks as in the MultiGrid tables, a slot
each for the objects and the background); an action decoder M_a learns latent actions -> actions on
the labelled subset and pseudo-labels every transition; a policy on one frame is cloned on the
pseudo-labels (eq. 8.7). Rows per label size:

- ``flam``: BC on FLAM's pseudo-labels of every transition;
- ``vanilla``: the same policy network and training on the labelled subset alone;
- ``idm``: BC on the pseudo-labels of a plain inverse dynamics model (the same decoder network on the
  frozen features of the frame pair, fitted on the same labels), VPT-style: ours, not the chapter's,
  to tell what the latent actions add over the frames they come from;

and once: ``all-labels`` (BC on every true label: the ceiling of pseudo-labelling), the expert, the
demonstrator (the expert with its random moves) and a uniformly random policy. Returns are means over
``--eval-episodes`` episodes on unseen seeds, actions sampled from the policy; each cloned policy's
``heldout_action_accuracy`` is the share of the demonstrator's actions it predicts (most likely
action) on ``--heldout-transitions`` demonstrations of unseen seeds. One torch thread.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import gymnasium as gym
import numpy as np
import torch

from causal.flam import FLAM, FLAMConfig, LAMTrainer, fit_autoencoder
from causal.flam_bc import (ActionDecoder, ClassifierTraining, FramePolicy, evaluate_policy, fit_classifier, predict,
                            pseudo_labels)
from causal.flam_nets import FSQAutoencoder
from causal.slots import frames_to_tensor
from envs.demonstrations import record_demonstrations
from envs.multigrid_agents import MultiGridGoalEnv, goal_expert_action
from envs.sprites import SpritesEnv, expert_action

EVAL_SEED = 1_000_000
"""Evaluation episodes reset with seeds from here (demonstrations use ``seed * 100_000`` onwards)."""


@dataclass(frozen=True)
class Args:
    env: str
    seed: int
    transitions: int
    labels: tuple[int, ...]
    epsilon: float
    num_fish: int
    num_agents: int
    ae_updates: int
    updates: int
    clip: int
    slot_dim: int
    action_dim: int
    beta_kl: float
    mask_binding: float
    lr: float
    decoder_updates: int
    bc_updates: int
    eval_episodes: int
    heldout_transitions: int
    out: str


def parse_args(argv: list[str] | None = None) -> Args:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", choices=("multigrid", "sprites"), default="sprites",
                   help="the game (see above): MultiGrid's goal task or the bigfish-like sprite game")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--transitions", type=int, default=30_000, help="demonstration transitions (whole episodes)")
    p.add_argument("--labels", type=int, nargs="+", default=[1000, 10_000], help="labelled subset sizes")
    p.add_argument("--epsilon", type=float, default=0.1, help="the demonstrator's share of random moves")
    p.add_argument("--num-fish", type=int, default=4, help="sprites: fish")
    p.add_argument("--num-agents", type=int, default=4, help="multigrid: agents, the player among them")
    p.add_argument("--ae-updates", type=int, default=300, help="FSQ autoencoder updates (eq. 8.1)")
    p.add_argument("--updates", type=int, default=2000, help="FLAM updates (eq. 8.6)")
    p.add_argument("--clip", type=int, default=4, help="frames per FLAM training clip")
    p.add_argument("--slot-dim", type=int, default=32)
    p.add_argument("--action-dim", type=int, default=8, help="d_a per slot")
    p.add_argument("--beta-kl", type=float, default=1e-3)
    p.add_argument("--mask-binding", type=float, default=0.0,
                   help="weight of the mask prior's binding term (FLAMConfig.mask_binding; 0: the prior alone)")
    p.add_argument("--lr", type=float, default=2e-3, help="FLAM's learning rate")
    p.add_argument("--decoder-updates", type=int, default=2000, help="updates of M_a and of the IDM baseline")
    p.add_argument("--bc-updates", type=int, default=3000, help="updates of every BC policy")
    p.add_argument("--eval-episodes", type=int, default=50)
    p.add_argument("--heldout-transitions", type=int, default=3000,
                   help="demonstrations of unseen seeds on which each policy's actions are scored against the demonstrator's")
    p.add_argument("--out", default="", help="write the results as JSON here")
    args = vars(p.parse_args(argv))
    parsed = Args(**{**args, "labels": tuple(args["labels"])})
    if parsed.transitions < 2 or not all(0 < n <= parsed.transitions for n in parsed.labels):
        p.error(f"--labels must lie in 1..--transitions ({parsed.transitions}), got {list(parsed.labels)}")
    if not 0 <= parsed.seed < EVAL_SEED // 100_000:
        p.error(f"--seed must be in 0..{EVAL_SEED // 100_000 - 1}: demonstrations reset with seeds from seed * 100,000, "
                f"evaluation from {EVAL_SEED:,}")
    if not 0.0 <= parsed.epsilon <= 1.0 or parsed.clip < 2 or min(parsed.eval_episodes, parsed.heldout_transitions) < 1:
        p.error("--epsilon must be in [0, 1], --clip >= 2, --eval-episodes and --heldout-transitions >= 1")
    if parsed.mask_binding < 0:
        p.error(f"--mask-binding must be >= 0, got {parsed.mask_binding}")
    try:
        game(parsed).make_env()
    except ValueError as error:
        p.error(f"--env {parsed.env}: {error}")
    return parsed


@dataclass(frozen=True)
class Game:
    """What the benchmark needs of a game: a fresh env, the expert's action and the frame with its
    labels in the env's current state, and the slots FLAM gets (a slot per labelled segment)."""

    make_env: Callable[[], gym.Env]
    expert: Callable[[gym.Env], int]
    scene: Callable[[gym.Env], tuple[np.ndarray, np.ndarray]]
    num_slots: int


def game(args: Args) -> Game:
    """``args.env``'s game: MultiGrid's goal task (the agents, the goal and the background get a slot
    each) or the sprite game (the agent, the fish and the background)."""
    if args.env == "multigrid":
        return Game(lambda: MultiGridGoalEnv(num_agents=args.num_agents), goal_expert_action,
                    lambda env: env.render_scene(), args.num_agents + 2)
    return Game(lambda: SpritesEnv(num_fish=args.num_fish), lambda env: expert_action(env._state, env.num_moves),
                lambda env: env.render_state(env._state), args.num_fish + 2)


def token_labels(labels: np.ndarray, stride: int = 4) -> torch.Tensor:
    """Each ``stride`` x ``stride`` feature token's segment ``[..., n]`` from pixel labels ``[..., H, W]``:
    the object with the most pixels in it, the background only where no object shows (the sprites are
    small: a token's corner pixel would miss most of them)."""
    pixels = torch.from_numpy(labels).long()
    onehot = torch.nn.functional.one_hot(pixels.flatten(0, -3), int(pixels.max()) + 1).permute(0, 3, 1, 2).float()
    shares = torch.nn.functional.avg_pool2d(onehot, stride)  # each segment's share of each token, as slots.token_masks
    shares[:, 0] *= 1e-3
    return shares.argmax(1).flatten(1).view(*pixels.shape[:-2], -1)


def clip_starts(episode_of_frame: np.ndarray, clip: int) -> torch.Tensor:
    """Frame indices where ``clip`` consecutive frames lie in one episode."""
    same = episode_of_frame[:len(episode_of_frame) - clip + 1] == episode_of_frame[clip - 1:]
    return torch.from_numpy(np.flatnonzero(same))


def train_flam(model: FLAM, features: torch.Tensor, labels: torch.Tensor, starts: torch.Tensor, args: Args) -> float:
    """Eq. 8.6 on random clips of ``args.clip`` frames within episodes, with the annealed mask prior; seconds."""
    trainer, start = LAMTrainer(model, seed=args.seed, mask_prior="annealed", total_updates=args.updates), time.time()
    generator = torch.Generator().manual_seed(args.seed)
    offsets = torch.arange(args.clip)
    for update in range(args.updates):
        frames = starts[torch.randint(len(starts), (model.config.batch_size,), generator=generator)][:, None] + offsets
        terms = trainer.update(features[frames], labels[frames])
        if update % 250 == 0 or update == args.updates - 1:
            print(f"  flam update {update}: {json.dumps({k: round(v, 4) for k, v in terms.items()})}", flush=True)
    return time.time() - start


@torch.no_grad()
def latent_actions(model: FLAM, features: torch.Tensor, current: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
    """Posterior means of every transition's latent actions ``[N, K * d_a]`` from its frame pair."""
    model.eval()
    pairs = [model.infer(features[torch.stack([c, c + 1], 1)]) for c in current.split(chunk)]
    return torch.cat(pairs).flatten(1)


def labelled_subsets(transitions: int, sizes: tuple[int, ...], seed: int) -> dict[int, torch.Tensor]:
    """Nested random subsets: the first ``n`` of one seeded permutation of the transitions, per size."""
    order = torch.randperm(transitions, generator=torch.Generator().manual_seed(seed + 7))
    return {n: order[:n] for n in sizes}


def main(args: Args) -> dict:
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    task = game(args)
    env = task.make_env()
    start = time.time()
    demos = record_demonstrations(env, args.transitions, args.seed * 100_000, args.epsilon, task.expert, task.scene)
    frames = torch.from_numpy(demos["frames"])
    current, actions = torch.from_numpy(demos["current"]), torch.from_numpy(demos["actions"])
    episode_of_frame = np.repeat(np.arange(len(demos["returns"])), np.bincount(demos["episode"]) + 1)
    print(f"demonstrations: {len(actions)} transitions, {len(demos['returns'])} episodes, mean return "
          f"{demos['returns'].mean():.2f} ({time.time() - start:.0f} s)", flush=True)
    results: dict = {"demonstrations": {"transitions": len(actions), "episodes": len(demos["returns"]),
                                        "return_mean": float(demos["returns"].mean()),
                                        "majority_action_share": float(np.bincount(demos["actions"]).max() / len(actions))}}

    config = FLAMConfig(num_slots=task.num_slots, slot_dim=args.slot_dim, action_dim=args.action_dim,
                        beta_kl=args.beta_kl, lr=args.lr, aggregator="broadcast", mask_binding=args.mask_binding)
    autoencoder = FSQAutoencoder(config.levels)
    start = time.time()
    fit_autoencoder(autoencoder, frames, args.ae_updates, seed=args.seed)
    with torch.no_grad():
        features = torch.cat([autoencoder.encode(frames_to_tensor(chunk)) for chunk in frames.split(4096)])
    print(f"autoencoder: {time.time() - start:.0f} s", flush=True)
    model = FLAM(replace(config), features.shape[1])
    seconds = train_flam(model, features, token_labels(demos["labels"]), clip_starts(episode_of_frame, args.clip), args)
    alphas = latent_actions(model, features, current)
    pairs = torch.cat([features[current], features[current + 1]], 1).flatten(1)
    results["flam_train_seconds"] = round(seconds, 1)

    decoding = ClassifierTraining(updates=args.decoder_updates, batch_size=256)
    cloning = ClassifierTraining(updates=args.bc_updates)
    observations = frames[current]
    heldout = record_demonstrations(env, args.heldout_transitions, args.seed * 100_000 + 50_000, args.epsilon,
                                    task.expert, task.scene)
    heldout_frames = torch.from_numpy(heldout["frames"][heldout["current"]])
    heldout_actions = torch.from_numpy(heldout["actions"])

    def clone(targets: torch.Tensor, rows: torch.Tensor | None = None) -> dict[str, float]:
        torch.manual_seed(args.seed)
        policy = FramePolicy(env.action_space.n, env.frame_size)
        inputs = observations if rows is None else observations[rows]
        fit_classifier(policy, inputs, targets if rows is None else targets[rows], cloning, seed=args.seed)
        accuracy = float((predict(policy, heldout_frames) == heldout_actions).float().mean())
        return {**evaluate_policy(policy, task.make_env, args.eval_episodes, EVAL_SEED), "heldout_action_accuracy": accuracy}

    for n, rows in labelled_subsets(len(actions), args.labels, args.seed).items():
        row: dict = {"vanilla": clone(actions, rows)}
        for name, inputs in (("flam", alphas), ("idm", pairs)):
            torch.manual_seed(args.seed)
            labels, accuracy = pseudo_labels(ActionDecoder(inputs.shape[1], env.action_space.n), inputs, rows, actions,
                                             decoding, seed=args.seed)
            row[name] = {**clone(labels), "pseudo_label_accuracy": accuracy}
        results[f"labels_{n}"] = row
        print(f"{n} labels: {json.dumps(row)}", flush=True)
    results["all_labels"] = clone(actions)
    rng = np.random.default_rng(args.seed)
    results["expert"] = evaluate_policy(None, task.make_env, args.eval_episodes, EVAL_SEED, act=task.expert)
    results["demonstrator"] = evaluate_policy(
        None, task.make_env, args.eval_episodes, EVAL_SEED,
        act=lambda e: rng.integers(e.action_space.n) if rng.random() < args.epsilon else task.expert(e))
    results["random"] = evaluate_policy(None, task.make_env, args.eval_episodes, EVAL_SEED,
                                        act=lambda e: rng.integers(e.action_space.n))
    print_table(results, args)
    if args.out:
        Path(args.out).write_text(json.dumps({"args": vars(args), "results": results}, indent=2))
    return results


def print_table(results: dict, args: Args) -> None:
    print(f"\nTable 8.4 analogue ({args.env}, seed {args.seed}): mean episodic return over {args.eval_episodes} "
          "unseen episodes")
    print(f"{'labels':>8} {'FLAM':>8} {'vanilla':>8} {'IDM':>8}  pseudo-label accuracy FLAM / IDM (the most "
          f"common action's share: {results['demonstrations']['majority_action_share']:.3f})")
    for n in args.labels:
        row = results[f"labels_{n}"]
        print(f"{n:>8} {row['flam']['return_mean']:8.2f} {row['vanilla']['return_mean']:8.2f} "
              f"{row['idm']['return_mean']:8.2f}  {row['flam']['pseudo_label_accuracy']:.3f} / "
              f"{row['idm']['pseudo_label_accuracy']:.3f}")
    print("held-out action accuracy of the cloned policies (FLAM / vanilla / IDM): " + ", ".join(
        f"{n}: " + " / ".join(f"{results[f'labels_{n}'][k]['heldout_action_accuracy']:.3f}" for k in ("flam", "vanilla", "idm"))
        for n in args.labels) + f", all labels: {results['all_labels']['heldout_action_accuracy']:.3f}")
    for name in ("all_labels", "expert", "demonstrator", "random"):
        print(f"{name:>12}: {results[name]['return_mean']:.2f}")


if __name__ == "__main__":
    main(parse_args())
