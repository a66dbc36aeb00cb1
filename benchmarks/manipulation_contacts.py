"""How often the skill collection policy makes the contacts behind manipulation's hard edges, and
what CMI a run learned for them.

The edges *from* ``unm`` and ``rand`` into the robot and ``mov`` exist only while they touch
(``envs/manipulation_truth.local_graph``). This counts, over ``--steps`` steps of the env-worker's
skill policy, the steps whose local graph has such an edge (and the steps holding ``mov``). Given a
run directory it prints, for those columns (``x``, ``y``; the constant ``z`` carries nothing):

* the largest CMI the run's graph-evaluator reported (``summary.json``: held-out episodes, EMA);
* the largest CMI of the run's last checkpointed model on the steps collected here, over all of
  them and over only the steps touching that cube. CMI is a mean over steps, so an effect present
  on a tenth of the steps is diluted tenfold: a high contact-step CMI with a low overall one says
  the model learned the contact and the data are too thin in it; a low contact-step CMI says the
  model has not learned it.

With ``--policy run`` the skills are picked by the run's checkpointed policy over skills (a run with
``--collector ppo``, e.g. PredDiff), sampled as its workers did, instead of uniformly: does the
learned collection make the contacts more often?

    python -m benchmarks.manipulation_contacts [--steps 3000] [--seed 0] [--run-dir runs/manip-long]
        [--policy uniform|run]
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from causal.cdl import CDLModel
from envs.manipulation import ManipulationEnv
from envs.manipulation_layout import EEF, GRP, MOV, RAND, UNM
from envs.manipulation_truth import ACTION
from envs.skills import SkillPolicy
from services.supervisor.evaluation import load_model

ROWS = np.r_[EEF, GRP, MOV]
SOURCES = {"unm": np.r_[UNM][:2], "rand": np.r_[RAND][:2]}
"""The x, y columns of each cube (z is constant in the scene's episodes)."""


@dataclass
class Collected:
    state: np.ndarray
    action: np.ndarray
    next_state: np.ndarray
    touching: dict[str, np.ndarray]
    """Per source cube: [steps] bool, the step's local graph has an edge from it into robot or mov."""
    holding: np.ndarray

    def fractions(self) -> dict[str, float]:
        out = {name: float(mask.mean()) for name, mask in self.touching.items()}
        out["holding mov"] = float(self.holding.mean())
        return out


def collect(steps: int, seed: int, chooser=None) -> Collected:
    """``steps`` steps of the skill policy (Uniform, or skills picked by ``chooser(obs)``), with each
    step's contacts from its local graph."""
    env = ManipulationEnv()
    policy = SkillPolicy(env.action_space, seed, chooser=chooser)
    obs, _ = env.reset(seed=seed)
    policy.reset()
    states, actions, nexts, graphs = [], [], [], []
    for _ in range(steps):
        action = policy.act(obs)
        next_obs, _, terminated, truncated, info = env.step(action)
        states.append(obs), actions.append(action), nexts.append(next_obs), graphs.append(info["local_graph"])
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()
            policy.reset()
    env.close()
    graph = np.asarray(graphs, dtype=bool)
    touching = {name: graph[:, ROWS][:, :, cols].any(axis=(1, 2)) for name, cols in SOURCES.items()}
    return Collected(np.asarray(states, np.float32), np.asarray(actions, np.float32), np.asarray(nexts, np.float32),
                     touching, graph[:, np.r_[MOV], ACTION].any(axis=1))


def reported_cmi(run_dir: Path) -> dict[str, float]:
    """Largest CMI (nats) the run's evaluator reported from unm's / rand's x, y into robot and mov."""
    summary = json.loads((run_dir / "summary.json").read_text())
    cmi, names = np.array(summary["cmi"]), summary["factor_names"]
    out = {}
    for name in SOURCES:
        cols = [i for i, n in enumerate(names) if n.startswith(f"{name}.") and not n.endswith(".z")]
        out[name] = float(cmi[np.ix_(ROWS, cols)].max())
    return out


def contact_cmi(model: CDLModel, data: Collected) -> dict[str, tuple[float, float]]:
    """Per source cube: (largest CMI over all steps, largest CMI over the steps touching it)."""
    tensors = [torch.from_numpy(x) for x in (data.state, data.action, data.next_state)]
    overall = model.cmi(*tensors).numpy()
    out = {}
    for name, cols in SOURCES.items():
        mask = torch.from_numpy(data.touching[name])
        local = model.cmi(*(t[mask] for t in tensors)).numpy() if mask.any() else np.zeros_like(overall)
        out[name] = (float(overall[np.ix_(ROWS, cols)].max()), float(local[np.ix_(ROWS, cols)].max()))
    return out


def run_chooser(run_dir: Path):
    """The run's checkpointed policy over skills, sampling options as its env-workers did."""
    from services.supervisor.analysis import load_policy
    from services.supervisor.config import load_run_config
    from services.supervisor.wiring import service_configs

    cfg = load_run_config(run_dir)
    policy_cfg = service_configs(cfg, "")["policy-learner"]
    chooser = load_policy(run_dir, policy_cfg, cfg, deterministic=False) if policy_cfg.skills else None
    if chooser is None:
        raise SystemExit(f"{run_dir} has no checkpointed policy over skills (run it with --collector ppo)")
    return chooser


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--run-dir", type=Path, default=None, help="a manipulation run to read learned CMI from")
    p.add_argument("--policy", choices=("uniform", "run"), default="uniform",
                   help="pick skills uniformly, or with --run-dir's learned policy over skills")
    args = p.parse_args(argv)
    if args.policy == "run" and args.run_dir is None:
        p.error("--policy run needs --run-dir")
    torch.set_num_threads(1)
    started = time.perf_counter()
    chooser = run_chooser(args.run_dir) if args.policy == "run" else None
    data = collect(args.steps, args.seed, chooser)
    print(f"{args.policy} skill policy, {args.steps:,} steps, seed {args.seed} ({time.perf_counter() - started:.0f}s):")
    for name, fraction in data.fractions().items():
        label = name if name == "holding mov" else f"touching {name}"
        print(f"  {label:<14}: {100 * fraction:5.1f}% of steps")
    if args.run_dir is not None:
        reported, model = reported_cmi(args.run_dir), load_model(args.run_dir)
        for name, (overall, local) in contact_cmi(model, data).items():
            print(f"  CMI {name} -> robot/mov (max, nats; threshold 0.02): evaluator {reported[name]:.4f}; "
                  f"checkpoint on these steps {overall:.4f}, on the steps touching {name} {local:.4f}")


if __name__ == "__main__":
    main()
