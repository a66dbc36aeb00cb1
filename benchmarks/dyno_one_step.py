"""One-step slot prediction of a ``--method dyno`` run's final world model, against copying the slots.

Transitions of ``chemical-pixels`` under uniformly random actions from a seed no run uses are drawn
as frames by the model's renderer, turned into slots by the model's slot encoder (no masks), and the
world model's prediction of the next frame's slots is scored by the matched squared error
(:func:`causal.dyno.matched_slot_mse`), beside copying the current slots and the slots' variance.
Chemical redraws positions every step, so part of the error is unpredictable by any model.

    python -m benchmarks.dyno_one_step --run-dir runs/<id> [--transitions 512]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from causal.dyno import matched_slot_mse
from services.runtime.checkpoint import load_checkpoint
from services.supervisor.evaluation import model_from_checkpoint

SEED = 20_000


def one_step(run_dir: Path, transitions: int) -> dict[str, float]:
    model = model_from_checkpoint(load_checkpoint(run_dir / "checkpoints" / "dynamics-learner-0.pt"))
    env = model.renderer()
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=SEED)
    states, actions, next_states = [], [], []
    for _ in range(transitions):
        action = int(rng.integers(env.action_space.n))
        following = env.step(action)[0]
        states.append(obs)
        actions.append(action)
        next_states.append(following)
        obs = following
    with torch.no_grad():
        now = model.slots(torch.from_numpy(env.render_states(np.stack(states))[0])).slots
        after = model.slots(torch.from_numpy(env.render_states(np.stack(next_states))[0])).slots
        step = model.world.step(now, torch.tensor(actions), model.world.initial_hidden(now))
        return {"world_model": float(matched_slot_mse(step.next_slots, after)),
                "copy": float(matched_slot_mse(now, after)), "slot_variance": float(after.var(dim=(0, 1)).mean())}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run-dir", type=Path, required=True)
    p.add_argument("--transitions", type=int, default=512)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    print(json.dumps(one_step(args.run_dir, args.transitions)))


if __name__ == "__main__":
    main()
