"""policy-learner core: policy-lag bound, PPO rollouts or SAC replay, abstraction mask, weights. No bus.

Versions are *published* policy versions: version 1 is the initial policy, published at start, and
each publication adds one. Version 0 marks data from the workers' random warm-up policy. A batch
produced by version ``v`` has lag ``self.version - v``; more than ``max_policy_lag`` and it is dropped.

PPO is on-policy: it needs the behaviour log-probabilities of the actions, which batches do not
carry. The learner keeps the published policies still within the lag bound and recomputes them
exactly with the version that produced the batch (random-policy data is dropped for PPO); the
values are the current critic's, as in IMPALA-style actor-learners.

With ``skills`` the policy acts over the skill options of :mod:`envs.skills` (the chapter's PPO over
skills on manipulation): a categorical PPO whose steps are decisions stitched from the batches by
:class:`~services.policy_learner.options.OptionStitcher`; a segment is ``skill_rollout`` decisions
of one worker.
"""
from __future__ import annotations

import copy
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from causal.abstraction import Abstraction
from causal.factored import FactorLayout
from causal.rl import ActionSpec, PPOAgent, RolloutBatch, SACAgent, UniformReplay, abstraction_input_mask
from causal.rl.base import as_batch
from causal.rl.ppo import ActorCritic
from envs.registry import ENVS
from proto.fits import check_fits
from proto.messages import EnvSpec, GraphReport, ScoredBatch, TransitionBatch, Weights
from services.policy_learner.config import PolicyLearnerConfig
from services.policy_learner.options import Decision, OptionStitcher
from causal.rl.policy_weights import MODEL, export_policy, policy_config_json
from services.runtime.checkpoint import load_checkpoint, save_checkpoint
from services.runtime.accept import VersionGate
from services.runtime.device import resolve_device

DROP_REASONS = ("stale", "future", "random_policy", "unknown_policy")


@dataclass(frozen=True)
class Verdict:
    """What happened to one incoming batch: its policy lag, and why it was dropped ('' if used)."""

    lag: int
    dropped: str = ""


@dataclass(frozen=True)
class _Segment:
    """One batch ready for PPO: time-major columns for a RolloutBatch."""

    obs: torch.Tensor
    actions: torch.Tensor
    log_probs: torch.Tensor
    rewards: torch.Tensor
    dones: torch.Tensor
    truncated: torch.Tensor
    next_obs: torch.Tensor


@torch.no_grad()
def _log_probs(net: ActorCritic, obs: np.ndarray, options: np.ndarray, device: torch.device) -> np.ndarray:
    dist = net.distribution(torch.from_numpy(obs).to(device))
    return dist.log_prob(torch.from_numpy(options).long().to(device)).cpu().numpy()


def _decision_segment(run: list[Decision]) -> _Segment:
    """Consecutive decisions of one worker as one PPO column (a decision is one step)."""
    flags = torch.tensor([[d.done, d.truncated] for d in run])
    return _Segment(torch.from_numpy(np.stack([d.obs for d in run])), torch.tensor([d.option for d in run]),
                    torch.tensor([d.log_prob for d in run], dtype=torch.float32),
                    torch.tensor([d.reward for d in run], dtype=torch.float32), flags[:, 0], flags[:, 1],
                    torch.from_numpy(np.stack([d.next_obs for d in run])))


def _stack(segments: list[_Segment], name: str) -> torch.Tensor:
    """One field of every segment as the columns of a time-major ``[T, N, ...]`` tensor."""
    return torch.stack([getattr(s, name) for s in segments], dim=1)


def skill_options(cfg: PolicyLearnerConfig, spec: EnvSpec) -> tuple[str, ...]:
    """The names of the options a policy over skills picks among (() for raw actions): those of the
    env's skill runner (its registry entry); ValueError for an env without one."""
    if not cfg.skills:
        return ()
    runner = ENVS[spec.env_id].skill_runner() if spec.env_id in ENVS else None
    if runner is None:
        raise ValueError(f"a policy over skills on {spec.env_id!r}, which has no skills")
    return tuple(runner.OPTION_NAMES)


def action_spec(spec: EnvSpec, cfg: PolicyLearnerConfig) -> ActionSpec:
    if cfg.skills:
        return ActionSpec("categorical", len(skill_options(cfg, spec)))
    if spec.action_kind == "categorical":
        return ActionSpec("categorical", spec.action_size)
    return ActionSpec("continuous", spec.action_size, (cfg.action_low,) * spec.action_size,
                      (cfg.action_high,) * spec.action_size)


class PolicyLearnerCore:
    """Turns (scored) transition batches into policy updates and versioned policy weights."""

    def __init__(self, cfg: PolicyLearnerConfig, spec: EnvSpec) -> None:
        self.cfg, self.spec = cfg, spec
        self.layout = FactorLayout.from_spec(spec)
        self.action = action_spec(spec, cfg)
        self.options = skill_options(cfg, spec)
        self.stitcher = OptionStitcher(cfg.skill_rollout) if cfg.skills else None
        if cfg.algo == "ppo":
            self.agent: PPOAgent | SACAgent = PPOAgent(spec.state_dim, self.action, cfg.ppo(), seed=cfg.seed)
        else:
            self.agent = SACAgent(spec.state_dim, self.action, cfg.sac(), seed=cfg.seed)
        self.device = resolve_device(cfg.device)
        """Where the agent learns (its networks and the behaviour policies' copies); batches and
        segments are kept on the CPU and moved for each computation."""
        self.agent.to(self.device)
        self.replay = UniformReplay(cfg.replay_capacity, spec.state_dim, spec.action_dim, seed=cfg.seed)
        self.version = 0
        self.behaviour: dict[int, ActorCritic] = {}
        self.pending: list[_Segment] = []
        self.updates = self.updates_since_publish = 0
        self.env_steps = 0
        self.dropped: Counter[str] = Counter()
        self.lags: Counter[str] = Counter()
        """Received batches by policy lag: ``"0"`` .. ``str(max_policy_lag)``, ``"over"`` (stale), ``"future"``."""
        self.graph_version = -1
        self.graph_versions = VersionGate(known=cfg.known_version)
        """The evaluator's report versions taken so far (ProtocolError for a jump past the bound)."""
        self.kept_factors: tuple[int, ...] | None = None
        prefixes = tuple(p.strip() for p in cfg.hide.split(",") if p.strip())
        self.hidden = frozenset(j for j, name in enumerate(self.layout.names) if name.startswith(prefixes))
        if self.hidden:
            self.agent.set_input_mask(abstraction_input_mask(
                self.layout, [j for j in range(self.layout.num_factors) if j not in self.hidden]))
        self.last_stats: dict[str, float] = {}

    def ingest(self, message: TransitionBatch | ScoredBatch) -> Verdict:
        """Bound the policy lag, then queue (PPO) or store (SAC) the batch.

        Raises ProtocolError('inconsistent') for a batch that does not fit the EnvSpec."""
        batch, intrinsic = (message.transitions, message.intrinsic_reward) if isinstance(message, ScoredBatch) \
            else (message, None)
        check_fits(self.spec, batch)
        lag = self.version - batch.policy_version
        self.lags[str(lag) if 0 <= lag <= self.cfg.max_policy_lag else "over" if lag > 0 else "future"] += 1
        reason = self._drop_reason(batch.policy_version, lag)
        if reason:
            self.dropped[reason] += 1
            return Verdict(lag, reason)
        self.env_steps += len(batch)
        reward = self.cfg.extrinsic_coef * batch.reward
        if intrinsic is not None:
            reward = reward + self.cfg.intrinsic_coef * intrinsic
        if self.stitcher is not None:
            net = self.behaviour[batch.policy_version]
            runs = self.stitcher.add(batch, reward, lambda obs, opt: _log_probs(net, obs, opt, self.device))
            self.pending.extend(_decision_segment(run) for run in runs)
        elif isinstance(self.agent, PPOAgent):
            self.pending.append(self._segment(batch, reward.astype(np.float32)))
        else:
            self.replay.add(batch.state, batch.action, reward, batch.next_state, batch.terminated)
        return Verdict(lag)

    def _drop_reason(self, version: int, lag: int) -> str:
        if lag < 0:
            return "future"
        if lag > self.cfg.max_policy_lag:
            return "stale"
        if isinstance(self.agent, PPOAgent) and version == 0:
            return "random_policy"
        if isinstance(self.agent, PPOAgent) and version not in self.behaviour:
            return "unknown_policy"
        return ""

    @torch.no_grad()
    def _segment(self, batch: TransitionBatch, reward: np.ndarray) -> _Segment:
        obs = torch.from_numpy(batch.state)
        net = self.behaviour[batch.policy_version]
        actions = torch.from_numpy(batch.action)
        actions = actions[:, 0].round().long() if self.action.kind == "categorical" else actions
        log_probs = net.distribution(obs.to(self.device)).log_prob(actions.to(self.device)).cpu()
        return _Segment(obs, actions, log_probs, torch.from_numpy(reward),
                        torch.from_numpy(batch.terminated | batch.truncated),
                        torch.from_numpy(batch.truncated & ~batch.terminated), torch.from_numpy(batch.next_state))

    @property
    def ready(self) -> bool:
        if isinstance(self.agent, PPOAgent):
            return len(self.pending) >= self.cfg.rollout_batches
        return len(self.replay) >= max(self.cfg.warmup_steps, self.cfg.batch_size)

    def train_step(self) -> dict[str, float]:
        """One PPO update on the pending rollout, or one SAC gradient step on the replay."""
        if isinstance(self.agent, PPOAgent):
            stats = self.agent.update(self._rollout())
        else:
            stats = self.agent.update(self.replay.sample(self.cfg.batch_size))
        self.updates += 1
        self.updates_since_publish += 1
        self.last_stats = stats
        return stats

    @torch.no_grad()
    def _rollout(self) -> RolloutBatch:
        """Pending segments of the first segment's length as the columns of one RolloutBatch."""
        steps = len(self.pending[0].rewards)
        columns = [s for s in self.pending if len(s.rewards) == steps][: self.cfg.rollout_batches]
        self.pending = [s for s in self.pending if all(s is not c for c in columns)]
        obs, next_obs, truncated = (_stack(columns, name) for name in ("obs", "next_obs", "truncated"))
        values = self.agent.net.value(obs.to(self.device)).cpu()
        bootstrap = self.agent.cfg.gamma * self.agent.net.value(next_obs.to(self.device)).cpu() * truncated.float()
        return RolloutBatch(obs, _stack(columns, "actions"), _stack(columns, "log_probs"), values,
                            _stack(columns, "rewards") + bootstrap, _stack(columns, "dones"), next_obs[-1],
                            policy_version=self.version)

    @property
    def publish_due(self) -> bool:
        return self.updates_since_publish >= self.cfg.publish_every

    def weights(self) -> Weights:
        """Publish the current policy as the next version (and remember it as a behaviour policy)."""
        self.version += 1
        self.updates_since_publish = 0
        if isinstance(self.agent, PPOAgent):
            self.behaviour[self.version] = copy.deepcopy(self.agent.net).requires_grad_(False)
            for old in [v for v in self.behaviour if v < self.version - self.cfg.max_policy_lag]:
                del self.behaviour[old]
        hidden = (self.cfg.hidden, self.cfg.hidden)
        return Weights(model=MODEL, version=self.version, tensors=export_policy(self.agent),
                       config_json=policy_config_json(self.cfg.algo, self.spec.state_dim, self.action, hidden,
                                                      self.options),
                       updates=self.updates, env_steps=self.env_steps)

    def apply_graph(self, report: GraphReport) -> bool:
        """Mask the policy input to the report's abstraction; True when the kept factors changed."""
        if not self.cfg.abstraction or report.weights_version < self.graph_version \
                or len(report.factor_names) != self.layout.num_factors \
                or not self.graph_versions.take("graph", report.weights_version):
            return False
        self.graph_version = report.weights_version
        kept = set(Abstraction(report.controllable, report.action_relevant, report.action_irrelevant).kept)
        suffix = self.cfg.always_keep
        kept |= {j for j, name in enumerate(self.layout.names) if suffix and name.endswith(suffix)}
        kept -= self.hidden
        if tuple(sorted(kept)) == self.kept_factors:
            return False
        self.kept_factors = tuple(sorted(kept))
        self.agent.set_input_mask(abstraction_input_mask(self.layout, self.kept_factors))
        return True

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Actions of the current policy (for evaluation and tests)."""
        return self.agent.act(as_batch(obs)[0].numpy())

    def checkpoint(self, path: Path) -> None:
        save_checkpoint({"agent": self.agent.state_dict(), "version": self.version, "updates": self.updates,
                         "env_steps": self.env_steps, "replay": self.replay.state_dict()}, path)

    def restore(self, path: Path) -> bool:
        """Resume; the next publication continues the version sequence. PPO behaviour policies are
        not saved, so batches of versions published before the restart are dropped ('unknown_policy')."""
        saved = load_checkpoint(path)
        if saved is None:
            return False
        self.agent.load_state_dict(saved["agent"])
        self.replay.load_state_dict(saved["replay"])
        self.version, self.updates = int(saved["version"]), int(saved["updates"])
        self.env_steps = int(saved["env_steps"])
        return True

    def _decision_stats(self) -> dict[str, float]:
        means = {f"return_{self.options[o]}": r for o, r in self.stitcher.mean_returns().items()}
        return {"decisions": self.stitcher.decisions, "decisions_discarded": self.stitcher.discarded, **means}

    def progress(self) -> dict[str, float]:
        return {"policy_version": self.version, "updates": self.updates, "env_steps": self.env_steps,
                "replay_size": len(self.replay), "pending_batches": len(self.pending),
                **(self._decision_stats() if self.stitcher is not None else {}),
                **{f"dropped_{k}": v for k, v in self.dropped.items()},
                **{f"lag_{k}": v for k, v in self.lags.items()}, **self.last_stats}
