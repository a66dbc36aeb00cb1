"""Fig. 5.4 (chapter 5.3.2): exploration with ELDEN vs PPO alone, dynamics curiosity and ensemble disagreement.

One run = one (env, intrinsic reward, seed): PPO (:class:`causal.rl.ppo.PPOAgent`) on the one-hot
state with the sparse task reward plus ``eta x r_intrinsic``, where the intrinsic model is trained
online on the agent's own transitions (Algorithm 6): each rollout is scored with the current model,
the policy is updated, the transitions join the model's replay and the model takes
``--dynamics-updates-per-step`` updates per env step. The rewards:

* ``none``: PPO alone (vanilla PPO of the chapter);
* ``elden``: :class:`causal.intrinsic.LocalGraphVariance` on an ELDEN ensemble
  (:class:`causal.elden_trainer.ELDENTrainer`, Mixup, gradient regulariser), zero for the first
  ``--warmup-steps`` env steps (Algorithm 6's warm-up; reference 20k);
* ``curiosity``: :class:`causal.intrinsic.PredictionError` (Burda et al. 2019) of one ELDEN attention
  model (``members = 1``): the same architecture as ELDEN's, as the chapter shares modules across methods;
* ``disagreement``: :class:`causal.intrinsic.Disagreement` of a :class:`causal.intrinsic.BootstrapEnsemble`
  (Pathak et al. 2019).

In process, without the bus: the point is the learning curves, so each run is one Python process
(``--workers`` of them at a time). Logged per PPO update: env steps, normalised stage count (stages
reached / stages of the task, chapter 5's y-axis) and success rate over the last ``--window`` finished
episodes, and the mean intrinsic reward of the rollout. Outputs under ``--out``: per run
``<env>-<reward>-s<seed>.json`` and ``.png``; per env ``<env>-comparison.png`` (mean +- standard error
over seeds) and ``<env>-summary.md``.

    python -m benchmarks.elden_exploration --envs cleaning-car --rewards none elden curiosity disagreement
        --seeds 0 1 2 --env-steps 30000 --out runs/elden-exploration --workers 2
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from causal.elden import ELDENConfig
from causal.elden_trainer import ELDENTrainer
from causal.factored import FactorLayout
from causal.intrinsic import BootstrapEnsemble, make_reward, score
from causal.replay import PrioritisedReplay, ReplayBuffer
from causal.rl.base import ActionSpec, RolloutBatch
from causal.rl.ppo import PPOAgent, PPOConfig
from causal.skild_agent import one_hot_states
from envs.registry import make_env

ENVS: dict[str, dict[str, Any]] = {"cleaning-car": {"task": "clean-rag"}, "thawing": {"task": "thaw-all"},
                                   "minecraft2d": {"goal": "diamond"}}
"""Chapter 5's tasks: CarWash (clean the car and the rag, 100 steps), Thawing (Mini-BEHAVIOR's: all
three foods), 2D Minecraft (the diamond)."""
REWARDS = ("none", "elden", "curiosity", "disagreement")
DISAGREEMENT_BATCH = ELDENConfig().batch_size
"""Rows per bootstrap-ensemble update: as many as an ELDEN update reads (5 members x 32)."""
SCORE_CHUNK = 32
"""Transitions per Jacobian batch of ELDEN's reward (measured fastest here: 10 ms per transition for 5
members on Cleaning Car, against 17 ms at 64 and 42 ms at 256)."""
COST_RANK = {"elden": 0, "curiosity": 1, "disagreement": 2, "none": 3}
"""Runs start dearest first, so a pool of workers ends together."""


@dataclass(frozen=True)
class ExplorationConfig:
    """One run's budget and knobs (defaults: the chapter's where they fit this machine's budgets)."""

    env: str = "cleaning-car"
    reward: str = "elden"
    seed: int = 0
    env_steps: int = 30_000
    num_envs: int = 8
    """Envs stepped together (reference: 20)."""
    rollout_steps: int = 128
    """Steps per env per PPO update (reference: 600; 20 x 600 would leave 2 updates in 30k steps)."""
    ppo_lr: float = 3e-4
    """PPO learning rate (reference 1e-4; raised for the short budgets here)."""
    gamma: float = 1.0
    """Discount (reference: 1 on these episodic tasks)."""
    eta: float = 1.0
    """Intrinsic reward coefficient beta (reference: 1; the chapter finds 1-10 work for ELDEN)."""
    warmup_steps: int = 5_000
    """Env steps before ELDEN's reward is non-zero (Algorithm 6; reference 20k of a longer run)."""
    dynamics_updates_per_step: float = 0.25
    """Intrinsic-model updates per env step (Algorithm 6: one per step)."""
    dynamics_lr: float = 1e-3
    """Adam rate of the ELDEN / curiosity models and of the bootstrap ensemble."""
    grad_reg: float = 1e-3
    """lambda of eqs. 5.2-5.3 (Table 5.2's best: 1e-3 CarWash, 1e-2 Thawing)."""
    prioritised: bool = False
    """Prioritised dynamics replay (the chapter: Minecraft and Kitchen only)."""
    window: int = 50
    """Finished episodes over which the curve's stage count and success are averaged."""
    log_every: int = 5_000
    """Print progress every this many env steps."""

    def __post_init__(self) -> None:
        if self.env not in ENVS:
            raise ValueError(f"unknown env {self.env!r}; known: {sorted(ENVS)}")
        if self.reward not in REWARDS:
            raise ValueError(f"unknown reward {self.reward!r}; known: {list(REWARDS)}")
        if self.env_steps < self.num_envs * self.rollout_steps:
            raise ValueError(f"env_steps ({self.env_steps}) is below one rollout ({self.num_envs * self.rollout_steps})")
        if min(self.num_envs, self.rollout_steps, self.window, self.log_every) < 1 or self.warmup_steps < 0:
            raise ValueError("num_envs, rollout_steps, window and log_every must be >= 1, warmup_steps >= 0")
        if not self.dynamics_updates_per_step >= 0 or not self.eta >= 0:
            raise ValueError("dynamics_updates_per_step and eta must be >= 0")

    @property
    def name(self) -> str:
        return f"{self.env}-{self.reward}-s{self.seed}"


class EnvBatch:
    """``num`` envs stepped together, reset when an episode ends; reports each finished episode's
    normalised stage count and success."""

    def __init__(self, env: str, num: int, seed: int) -> None:
        self.envs = [make_env(env, **ENVS[env]) for _ in range(num)]
        spec = self.envs[0].env_spec()
        self.layout = FactorLayout.from_spec(spec)
        self.sizes, self.actions = tuple(spec.factor_sizes), spec.action_size
        self.num_stages = len(self.envs[0].stage_names)
        self.seed, self.episodes = seed, 0
        self.states = np.stack([self._reset(e) for e in self.envs])

    def _reset(self, env: Any) -> np.ndarray:
        self.episodes += 1
        return env.reset(seed=self.seed * 1_000_003 + self.episodes)[0].astype(np.int64)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[float, float]]]:
        """``(next states, task rewards, episode ended, [(stages reached / stages, success)] of ended ones)``;
        ``self.states`` moves on to the states after resets."""
        nxt, rewards, ended = self.states.copy(), np.zeros(len(self.envs)), np.zeros(len(self.envs), bool)
        finished = []
        for i, (env, a) in enumerate(zip(self.envs, actions)):
            obs, rewards[i], terminated, truncated, info = env.step(int(a))
            nxt[i], ended[i] = obs, terminated or truncated
            if ended[i]:
                finished.append((min(info["num_stages"] / self.num_stages, 1.0), float(info["success"])))
        self.states = nxt.copy()
        for i in np.flatnonzero(ended):
            self.states[i] = self._reset(self.envs[i])
        return nxt, rewards, ended, finished


class IntrinsicModel:
    """The run's intrinsic reward and the model it reads, trained online on the agent's transitions."""

    def __init__(self, cfg: ExplorationConfig, layout: FactorLayout) -> None:
        self.cfg, self.seen = cfg, 0
        self.reward = make_reward(cfg.reward, cfg.eta) if cfg.reward != "none" else None
        self.trainer: ELDENTrainer | None = None
        self.ensemble: BootstrapEnsemble | None = None
        if cfg.reward in ("elden", "curiosity"):
            members = 5 if cfg.reward == "elden" else 1
            model_cfg = ELDENConfig(members=members, lr=cfg.dynamics_lr, grad_reg=cfg.grad_reg,
                                    prioritised=cfg.prioritised, reward_warmup_env_steps=cfg.warmup_steps)
            self.trainer = ELDENTrainer(layout, model_cfg, seed=cfg.seed)
            buffer = PrioritisedReplay if cfg.prioritised else ReplayBuffer
            self.replay = buffer(max(cfg.env_steps, 1), layout.state_dim, 1, seed=cfg.seed)
        elif cfg.reward == "disagreement":
            self.ensemble = BootstrapEnsemble(layout, lr=cfg.dynamics_lr, capacity=max(cfg.env_steps, 1), seed=cfg.seed)

    @property
    def model(self) -> torch.nn.Module | None:
        return self.trainer.model if self.trainer is not None else self.ensemble

    def rewards(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray) -> np.ndarray:
        """``eta x r_intrinsic`` of these transitions from the current model; 0 before the reward's warm-up."""
        if self.reward is None or self.seen < self.reward.warmup_env_steps(self.model) or self.seen == 0:
            return np.zeros(len(state), np.float32)
        return score(self.reward, self.model, np.ones((1, 1), bool), state, action, next_state, chunk=SCORE_CHUNK)

    def learn(self, state: np.ndarray, action: np.ndarray, next_state: np.ndarray) -> None:
        """Add the transitions and take ``dynamics_updates_per_step`` updates per transition."""
        self.seen += len(state)
        if self.reward is None:
            return
        state, action, next_state = (np.asarray(x, np.float32) for x in (state, action, next_state))
        updates = int(round(self.cfg.dynamics_updates_per_step * len(state)))
        if self.ensemble is not None:
            self.ensemble.add(state, action, next_state)
            for _ in range(updates):
                self.ensemble.train_step(DISAGREEMENT_BATCH)
            return
        self.replay.add(state, action, next_state)
        for _ in range(updates):
            self._update()

    def _update(self) -> None:
        if not isinstance(self.replay, PrioritisedReplay):
            self.trainer.update(*self.replay.sample(self.trainer.batch_size))
            return
        index, batch = self.replay.sample_indexed(self.trainer.batch_size)
        self.trainer.update(*batch)
        if self.trainer.last_priorities is not None:
            self.replay.update_priorities(index, self.trainer.last_priorities)


def run(cfg: ExplorationConfig) -> dict[str, Any]:
    """One run; the curve per PPO update and the CPU seconds spent."""
    torch.set_num_threads(1)
    torch.manual_seed(cfg.seed)
    envs = EnvBatch(cfg.env, cfg.num_envs, cfg.seed)
    ppo = PPOAgent(int(sum(envs.sizes)), ActionSpec("categorical", envs.actions),
                   PPOConfig(lr=cfg.ppo_lr, gamma=cfg.gamma, num_envs=cfg.num_envs, rollout_steps=cfg.rollout_steps),
                   seed=cfg.seed)
    intrinsic = IntrinsicModel(cfg, envs.layout)
    curve: dict[str, list[float]] = {k: [] for k in ("env_steps", "stages", "success", "intrinsic_mean", "episodes")}
    recent: list[tuple[float, float]] = []
    steps, episodes, next_log, start = 0, 0, cfg.log_every, time.process_time()
    while steps < cfg.env_steps:
        batch, transitions, finished = _rollout(ppo, envs, cfg.rollout_steps)
        bonus = intrinsic.rewards(*transitions).reshape(batch.rewards.shape)
        ppo.update(replace(batch, rewards=batch.rewards + torch.from_numpy(bonus)))
        intrinsic.learn(*transitions)
        steps, episodes = steps + transitions[0].shape[0], episodes + len(finished)
        recent = (recent + finished)[-cfg.window:]
        for key, value in (("env_steps", steps), ("stages", _mean([s for s, _ in recent])),
                           ("success", _mean([w for _, w in recent])), ("intrinsic_mean", float(bonus.mean())),
                           ("episodes", episodes)):
            curve[key].append(value)
        if steps >= next_log or steps >= cfg.env_steps:
            next_log += cfg.log_every
            print(f"{cfg.name}: {steps} steps, stages {curve['stages'][-1]:.3f}, success {curve['success'][-1]:.2f}, "
                  f"r_i {curve['intrinsic_mean'][-1]:.4f}, {time.process_time() - start:.0f} CPU s", flush=True)
    return {"config": asdict(cfg), "num_stages": envs.num_stages, "curve": curve,
            "final_stages": curve["stages"][-1], "final_success": curve["success"][-1],
            "cpu_s": time.process_time() - start}


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else 0.0


def _rollout(ppo: PPOAgent, envs: EnvBatch, steps: int
             ) -> tuple[RolloutBatch, tuple[np.ndarray, np.ndarray, np.ndarray], list[tuple[float, float]]]:
    """``steps`` steps of every env: the PPO batch (task rewards), the transitions ``(s, a, s')``
    flattened step-major, and the finished episodes."""
    obs, acts, logps, values, rewards, dones, s, a, n, finished = ([] for _ in range(10))
    for _ in range(steps):
        x = one_hot_states(envs.states, envs.sizes)
        step = ppo.policy_step(x)
        before = envs.states
        nxt, reward, ended, done = envs.step(np.asarray(step.env_actions, np.int64))
        finished += done
        obs.append(x), acts.append(step.actions), logps.append(step.log_probs), values.append(step.values)
        rewards.append(torch.as_tensor(reward, dtype=torch.float32)), dones.append(torch.as_tensor(ended))
        s.append(before), a.append(np.asarray(step.env_actions)[:, None]), n.append(nxt)
    batch = RolloutBatch(torch.stack(obs), torch.stack(acts), torch.stack(logps), torch.stack(values),
                         torch.stack(rewards), torch.stack(dones), one_hot_states(envs.states, envs.sizes))
    return batch, (np.concatenate(s), np.concatenate(a), np.concatenate(n)), finished


def run_and_save(cfg: ExplorationConfig, out: Path) -> dict[str, Any]:
    """:func:`run`, then its JSON and learning-curve PNG under ``out``."""
    result = run(cfg)
    (out / f"{cfg.name}.json").write_text(json.dumps(result, indent=1))
    from benchmarks.elden_exploration_plots import plot_run
    plot_run(result, out / f"{cfg.name}.png")
    return result


def _run_job(job: tuple[ExplorationConfig, Path]) -> dict[str, Any]:
    return run_and_save(*job)


def main(configs: list[ExplorationConfig], out: Path, workers: int = 1) -> list[dict[str, Any]]:
    """Every run (``workers`` processes at a time), then one comparison plot and table per env."""
    from benchmarks.elden_exploration_plots import plot_comparison, summary_markdown
    out.mkdir(parents=True, exist_ok=True)
    wall = time.time()
    jobs = [(cfg, out) for cfg in sorted(configs, key=lambda c: COST_RANK[c.reward])]
    if workers > 1:
        with multiprocessing.get_context("spawn").Pool(workers) as pool:
            results = pool.map(_run_job, jobs, chunksize=1)
    else:
        results = [_run_job(job) for job in jobs]
    for env in dict.fromkeys(c.env for c in configs):
        mine = [r for r in results if r["config"]["env"] == env]
        plot_comparison(mine, out / f"{env}-comparison.png")
        text = summary_markdown(mine)
        (out / f"{env}-summary.md").write_text(text)
        print(text)
    print(f"wall {time.time() - wall:.0f} s; CPU s per run {[round(r['cpu_s']) for r in results]}", flush=True)
    return results


def parse(argv: list[str] | None = None) -> tuple[list[ExplorationConfig], Path, int]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=["cleaning-car"])
    parser.add_argument("--rewards", nargs="+", default=list(REWARDS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--env-steps", type=int, default=ExplorationConfig.env_steps)
    parser.add_argument("--out", type=Path, default=Path("runs/elden-exploration"))
    parser.add_argument("--workers", type=int, default=1)
    knobs = {"num_envs": int, "rollout_steps": int, "ppo_lr": float, "gamma": float, "eta": float,
             "warmup_steps": int, "dynamics_updates_per_step": float, "dynamics_lr": float, "grad_reg": float,
             "window": int, "log_every": int}
    for name, kind in knobs.items():
        parser.add_argument("--" + name.replace("_", "-"), type=kind, default=getattr(ExplorationConfig, name))
    parser.add_argument("--prioritised", action="store_true", help="prioritised dynamics replay (ch. 5: Minecraft)")
    args = parser.parse_args(argv)
    for env in args.envs:
        if env not in ENVS:
            parser.error(f"unknown env {env!r}; known: {', '.join(ENVS)}")
    for reward in args.rewards:
        if reward not in REWARDS:
            parser.error(f"unknown reward {reward!r}; known: {', '.join(REWARDS)}")
    if args.workers < 1:
        parser.error("--workers must be >= 1")
    try:
        configs = [ExplorationConfig(env=e, reward=r, seed=s, env_steps=args.env_steps, prioritised=args.prioritised,
                                     **{k: getattr(args, k) for k in knobs})
                   for e in args.envs for r in args.rewards for s in args.seeds]
    except ValueError as error:
        parser.error(str(error))
    return configs, args.out, args.workers


if __name__ == "__main__":
    main(*parse())
