"""policy-learner core for SkiLD (ch. 6): reward-free skill pre-training, then task learning over the
frozen skills. No bus; the pure parts are :mod:`causal.skild`, :mod:`causal.skild_agent`.

Phases (:func:`phase_for`): ``pretrain`` until ``skild_pretrain_steps`` env steps of skill data were
taken in, then ``task``. In ``pretrain`` each :class:`~proto.messages.SkillBatch` (with its induced
local graphs: the evaluator's :class:`~proto.messages.InducedGraphs`, joined by ``(worker, seq)``, or
the simulator's true ones, the chapter's ablation) updates the graph history, fills the skill replay,
and its skill segments (``started`` steps) become the graph selector's samples, rewarded with eq.
6.1's novelty; the skill Q-network (double DQN, hindsight relabelled, eq. 6.2) and the DIAYN
discriminator update ``skild_updates_per_env_step`` times per step taken in; the switch waits until
the budget's updates are done (:attr:`SkildLearnerCore.owed_updates`). At the switch the
history's targets are frozen as the task policy's options (``slot * K + b``), the low level stops
learning, and a PPO task policy learns from the task reward summed over each skill's steps (the
decisions stitched per worker as for PPO over skills, :class:`~services.policy_learner.options.
OptionStitcher`). Every publication carries the phase, so workers switch with the weights; batches
of the other phase are dropped (``phase``).

The induced-graph coverage (:class:`EpisodeCoverage`): per phase, the share of finished episodes in
which each object-level dependency (a graph row, ``"table, printer -> printer"``) was induced at
least once.
"""
from __future__ import annotations

import copy
import zlib
from collections import Counter
from dataclasses import replace

import numpy as np
import torch

from causal.rl import PPOAgent, RolloutBatch
from causal.rl.ppo import ActorCritic
from causal.skild import novelty_reward, object_graphs, object_names, row_keys
from causal.skild_agent import SkiLDAgent, one_hot_states
from causal.skild_policy import MODEL, SkildPolicyConfig, export_tensors, task_agent
from causal.skild_pretrain import describe_row, multi_object
from proto.codec import ProtocolError
from proto.fits import check_fits
from proto.messages import EnvSpec, InducedGraphs, SkillBatch, TransitionBatch, Weights
from services.policy_learner.config import PolicyLearnerConfig
from services.policy_learner.options import Decision, OptionStitcher
from services.runtime.checkpoint import load_checkpoint, save_checkpoint

DROP_REASONS = ("phase", "stale", "future", "unknown_policy", "no_graphs")
MAX_WAITING = 64
"""SkillBatches held for their induced graphs; the oldest is dropped (``no_graphs``) beyond this."""


def phase_for(pretrain_steps_taken: int, budget: int) -> str:
    """The phase after ``pretrain_steps_taken`` env steps of pre-training data: the budget drives it."""
    return "pretrain" if pretrain_steps_taken < budget else "task"


class EpisodeCoverage:
    """Per phase: finished episodes, and in how many of them each object-level graph row was induced."""

    def __init__(self, num_factors: int) -> None:
        self.n = num_factors
        self.running: dict[tuple[str, int], set[tuple[int, int]]] = {}
        self.episodes: Counter[str] = Counter()
        self.hits: dict[str, Counter[tuple[int, int]]] = {}

    def add(self, phase: str, worker: str, episode_id: np.ndarray, induced: np.ndarray, ended: np.ndarray) -> None:
        keys = row_keys(induced)
        for t in range(len(episode_id)):
            seen = self.running.setdefault((worker, int(episode_id[t])), set())
            seen.update(zip(range(self.n), keys[t].tolist()))
            if ended[t]:
                self.episodes[phase] += 1
                self.hits.setdefault(phase, Counter()).update(self.running.pop((worker, int(episode_id[t]))))
        if len(self.running) > 4096:  # episodes whose end was lost with a dropped batch
            for key in list(self.running)[:-1024]:
                del self.running[key]

    def shares(self, phase: str) -> dict[tuple[int, int], float]:
        total = self.episodes[phase]
        return {row: n / total for row, n in self.hits.get(phase, Counter()).items()} if total else {}

    def named(self, phase: str, objects: tuple[str, ...], interactions_only: bool = True) -> dict[str, float]:
        """``{"table, printer -> printer": share}``, multi-object rows only by default."""
        width = len(objects) + 1
        return {describe_row(f, k, objects): share for (f, k), share in sorted(self.shares(phase).items())
                if not interactions_only or multi_object(f, k, width)}

    def state_dict(self) -> dict:
        return {"episodes": dict(self.episodes), "hits": {p: [[f, k, n] for (f, k), n in c.items()]
                                                          for p, c in self.hits.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.episodes = Counter(state["episodes"])
        self.hits = {p: Counter({(int(f), int(k)): int(n) for f, k, n in rows}) for p, rows in state["hits"].items()}


def _decision_columns(runs: list[list[Decision]], sizes: tuple[int, ...]) -> dict[str, torch.Tensor]:
    """Runs of decisions as time-major ``[T, N]`` columns (observations one-hot)."""
    def stack(fn) -> torch.Tensor:
        return torch.stack([torch.stack([fn(d) for d in run]) for run in runs], dim=1)
    return {"obs": stack(lambda d: one_hot_states(d.obs[None].astype(np.int64), sizes)[0]),
            "next_obs": stack(lambda d: one_hot_states(d.next_obs[None].astype(np.int64), sizes)[0]),
            "actions": stack(lambda d: torch.tensor(d.option)),
            "log_probs": stack(lambda d: torch.tensor(d.log_prob, dtype=torch.float32)),
            "rewards": stack(lambda d: torch.tensor(d.reward, dtype=torch.float32)),
            "dones": stack(lambda d: torch.tensor(d.done)), "truncated": stack(lambda d: torch.tensor(d.truncated))}


class SkildLearnerCore:
    """SkiLD's skill policy, graph selector and task policy, learned from SkillBatches; versioned weights."""

    def __init__(self, cfg: PolicyLearnerConfig, spec: EnvSpec) -> None:
        if any(kind != "categorical" for kind in spec.factor_kinds) or spec.action_kind != "categorical":
            raise ValueError(f"SkiLD learns over categorical factors and actions; {spec.env_id} has others")
        self.cfg, self.spec = cfg, spec
        self.sizes, self.objects = tuple(spec.factor_sizes), object_names(spec.factor_objects)
        self.skild = cfg.models.skild
        self.agent = SkiLDAgent(self.sizes, len(self.objects), spec.action_size, self.skild, cfg.skill, "skild", cfg.seed)
        self.phase = "pretrain"
        self.task: PPOAgent | None = None
        self.behaviour: dict[int, ActorCritic] = {}
        self.version = self.updates = self.task_updates = self.selector_updates = self.since_publish = 0
        self.pretrain_steps = self.task_steps = 0
        self.dropped: Counter[str] = Counter()
        self.waiting: dict[tuple[str, int], SkillBatch] = {}
        self.graphs: dict[tuple[str, int], InducedGraphs] = {}
        self.selector_stitcher, self.task_stitcher = OptionStitcher(1), OptionStitcher(cfg.skill_rollout)
        self.segments: list[Decision] = []
        self.pending: list[list[Decision]] = []
        self.coverage = EpisodeCoverage(len(self.objects))
        self.last_stats: dict[str, float] = {}

    # ------------------------------------------------------------------ ingest

    @property
    def env_steps(self) -> int:
        return self.pretrain_steps + self.task_steps

    def ingest(self, message: SkillBatch | InducedGraphs) -> str:
        """Take a SkillBatch (or the induced graphs one waits for); '' if used, else why dropped.
        ProtocolError('inconsistent') for a batch that does not fit the EnvSpec or the graph source."""
        if isinstance(message, InducedGraphs):
            return self._graphs_arrived(message)
        batch = message.transitions
        check_fits(self.spec, batch)
        reason = self._drop_reason(message)
        if reason:
            self.dropped[reason] += 1
            return reason
        if self.cfg.skild_graphs == "true":
            if batch.local_graph is None:
                raise ProtocolError("inconsistent", "SkillBatch without true local graphs (skild_graphs=true)")
            return self._take(message, batch.local_graph)
        key = (batch.worker_id, batch.seq)
        if key in self.graphs:
            return self._take(message, self.graphs.pop(key).graphs)
        self.waiting[key] = message
        while len(self.waiting) > MAX_WAITING:
            self.waiting.pop(next(iter(self.waiting)))
            self.dropped["no_graphs"] += 1
        return ""

    def _graphs_arrived(self, graphs: InducedGraphs) -> str:
        key = (graphs.worker_id, graphs.seq)
        d = self.spec.num_factors
        if graphs.graphs.shape[1:] != (d, d + 1):
            raise ProtocolError("inconsistent", f"InducedGraphs of shape {graphs.graphs.shape} for {d} factors")
        waiting = self.waiting.pop(key, None)
        if waiting is None:
            self.graphs[key] = graphs
            while len(self.graphs) > MAX_WAITING:
                self.graphs.pop(next(iter(self.graphs)))
            return ""
        if len(graphs.graphs) != len(waiting.transitions):
            raise ProtocolError("inconsistent", f"InducedGraphs of {len(graphs.graphs)} steps for a batch of "
                                                f"{len(waiting.transitions)}")
        if waiting.phase != self.phase:
            self.dropped["phase"] += 1
            return "phase"
        return self._take(waiting, graphs.graphs)

    def _drop_reason(self, message: SkillBatch) -> str:
        lag = self.version - message.transitions.policy_version
        if message.phase != self.phase:
            return "phase"
        if lag < 0:
            return "future"
        if self.phase == "task" and lag > self.cfg.max_policy_lag:
            return "stale"
        if self.phase == "task" and message.transitions.policy_version not in self.behaviour:
            return "unknown_policy"
        return ""

    def _take(self, message: SkillBatch, graphs: np.ndarray) -> str:
        batch = message.transitions
        induced = object_graphs(graphs, self.spec.factor_objects)
        self.coverage.add(self.phase, batch.worker_id, batch.episode_id, induced, batch.terminated | batch.truncated)
        if self.phase == "pretrain":
            self._take_pretrain(message, induced)
        else:
            self._take_task(message)
        return ""

    def _labels(self, slot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Target ``(factor, row)`` per step; slot -1 (no target yet): factor 0, the empty row."""
        factors, rows = self.agent.history.target_arrays(len(self.objects) + 1)
        if (slot >= len(factors)).any():
            raise ProtocolError("inconsistent", f"skill slot {int(slot.max())} of {len(factors)} targets")
        known = slot >= 0
        factor = np.where(known, factors[np.maximum(slot, 0)] if len(factors) else 0, 0).astype(np.int64)
        row = np.where(known[:, None], rows[np.maximum(slot, 0)] if len(rows) else False, False)
        return factor, row

    def _take_pretrain(self, message: SkillBatch, induced: np.ndarray) -> None:
        batch = message.transitions
        factor, row = self._labels(message.slot)
        counts = self.agent.observe(state=batch.state.astype(np.int64), action=batch.action[:, 0].astype(np.int64),
                                    next_state=batch.next_state.astype(np.int64), terminated=batch.terminated,
                                    induced=induced, factor=factor, row=row, b=message.b.astype(np.int64),
                                    stream=np.full(len(batch), zlib.crc32(batch.worker_id.encode())),
                                    episode=batch.episode_id, step=batch.step.astype(np.int64))
        self.pretrain_steps += len(batch)
        if self.version - batch.policy_version <= self.cfg.max_policy_lag:
            option = np.where(message.started & (message.slot >= 0), message.slot, -1).astype(np.int32)
            runs = self.selector_stitcher.add(_with_option(batch, option), novelty_reward(counts),
                                              lambda obs, opt: np.zeros(len(opt)))
            self.segments.extend(d for run in runs for d in run)

    def _take_task(self, message: SkillBatch) -> None:
        batch = message.transitions
        k = self.agent.k
        option = np.where(message.started, np.maximum(message.slot, 0) * k + message.b, -1).astype(np.int32)
        net = self.behaviour[batch.policy_version]

        def log_probs(obs: np.ndarray, options: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                x = one_hot_states(obs.astype(np.int64), self.sizes)
                return net.distribution(x).log_prob(torch.as_tensor(options).long()).numpy()

        self.pending.extend(self.task_stitcher.add(_with_option(batch, option),
                                                   self.cfg.extrinsic_coef * batch.reward, log_probs))
        self.task_steps += len(batch)

    # ------------------------------------------------------------------ learning

    @property
    def ready(self) -> bool:
        if self.phase == "task":
            return len(self.pending) >= self.cfg.rollout_batches
        return self._skill_update_due or len(self.segments) >= self.cfg.skill.selector_batch

    @property
    def _skill_update_due(self) -> bool:
        """A skill update is due: the replay holds ``learning_starts`` steps and fewer than
        ``skild_updates_per_env_step`` updates per pre-training step taken in were done."""
        return self.agent.replay.size >= self.cfg.skill.learning_starts \
            and self.updates < self.cfg.skild_updates_per_env_step * self.pretrain_steps

    def train_step(self) -> dict[str, float]:
        """Pre-training: a skill-Q / discriminator update and, when enough segments are in, a selector
        update. Task: one PPO update of the task policy."""
        if self.phase == "task":
            self.last_stats = self._task_update()
            self.task_updates += 1
        else:
            stats: dict[str, float] = {}
            if self._skill_update_due:
                stats = self.agent.update()
                self.updates += 1
            if len(self.segments) >= self.cfg.skill.selector_batch and self.agent.history.targets:
                stats.update(self._selector_update())
            elif len(self.segments) >= self.cfg.skill.selector_batch:
                self.segments = []
            self.last_stats = {**self.last_stats, **stats}
        self.since_publish += 1
        return self.last_stats

    def _selector_update(self) -> dict[str, float]:
        batch, self.segments = self.segments[: self.cfg.skill.selector_batch], self.segments[self.cfg.skill.selector_batch:]
        self.selector_updates += 1
        states = np.stack([d.obs for d in batch]).astype(np.int64)
        return self.agent.update_selector(self.agent.features(states), np.array([d.option for d in batch]),
                                          np.array([d.reward for d in batch]))

    def _task_update(self) -> dict[str, float]:
        runs, self.pending = self.pending[: self.cfg.rollout_batches], self.pending[self.cfg.rollout_batches:]
        c = _decision_columns(runs, self.sizes)
        with torch.no_grad():
            values = self.task.net.value(c["obs"])
            bootstrap = self.task.cfg.gamma * self.task.net.value(c["next_obs"]) * c["truncated"].float()
        return self.task.update(RolloutBatch(c["obs"], c["actions"], c["log_probs"], values, c["rewards"] + bootstrap,
                                             c["dones"], c["next_obs"][-1], policy_version=self.version))

    @property
    def owed_updates(self) -> float:
        """Skill updates pre-training still owes before the switch: ``skild_updates_per_env_step`` per env
        step of the budget taken in, less those done (0 while the replay holds fewer than
        ``learning_starts`` steps, when no update can run). The switch waits for them, so the budget buys
        the same number of skill updates however the batches arrive: a burst that spends the whole budget
        in one drain of the inbox (a slow first publish on a loaded machine) would otherwise end
        pre-training with no update at all."""
        if self.agent.replay.size < self.cfg.skill.learning_starts:
            return 0.0
        taken = min(self.pretrain_steps, self.cfg.skild_pretrain_steps)
        return max(0.0, self.cfg.skild_updates_per_env_step * taken - self.updates)

    def maybe_switch(self) -> bool:
        """Switch to task learning once the pre-training budget is spent and its skill updates are done
        (True when it just did)."""
        if self.phase == "task" or phase_for(self.pretrain_steps, self.cfg.skild_pretrain_steps) == "pretrain":
            return False
        if self.owed_updates > 0:
            return False
        self.phase = "task"
        self.task = task_agent(self._policy_config(), self.cfg.ppo(), seed=self.cfg.seed)
        self.waiting.clear()
        self.since_publish = self.cfg.publish_every  # publish the task policy at once
        return True

    @property
    def epsilon(self) -> float:
        s = self.cfg.skill
        return max(s.eps_end, s.eps_start - (s.eps_start - s.eps_end) * self.pretrain_steps / max(s.eps_decay_steps, 1))

    def _policy_config(self) -> SkildPolicyConfig:
        return SkildPolicyConfig(phase=self.phase, sizes=self.sizes, num_factors=len(self.objects),
                                 actions=self.spec.action_size, k=self.agent.k, hidden=self.cfg.skill.hidden,
                                 selector_slots=self.skild.max_targets, skill_steps=self.skild.skill_steps,
                                 epsilon=self.epsilon, targets=tuple(self.agent.history.targets),
                                 task_hidden=(self.cfg.hidden, self.cfg.hidden))

    # ------------------------------------------------------------------ publishing

    @property
    def publish_due(self) -> bool:
        every = self.cfg.publish_every_updates or (1 if self.phase == "task" else 50)
        return self.since_publish >= every

    def weights(self) -> Weights:
        self.version += 1
        self.since_publish = 0
        nets = {"q": self.agent.q, "selector": self.agent.selector}
        if self.task is not None:
            nets["task"] = self.task.net
            self.behaviour[self.version] = copy.deepcopy(self.task.net).requires_grad_(False)
            for old in [v for v in self.behaviour if v < self.version - self.cfg.max_policy_lag]:
                del self.behaviour[old]
        return Weights(model=MODEL, version=self.version, config_json=self._policy_config().to_json(),
                       tensors=export_tensors(nets), updates=self.updates + self.task_updates, env_steps=self.env_steps)

    # ------------------------------------------------------------------ checkpoint, progress

    def checkpoint(self, path) -> None:
        a = self.agent
        state = {"phase": self.phase, "version": self.version, "updates": self.updates, "task_updates": self.task_updates,
                 "pretrain_steps": self.pretrain_steps, "task_steps": self.task_steps, "agent_updates": a.updates,
                 "q": a.q.state_dict(), "q_target": a.q_target.state_dict(), "q_opt": a.q_opt.state_dict(),
                 "disc": a.disc.state_dict(), "disc_opt": a.disc_opt.state_dict(), "selector": a.selector.state_dict(),
                 "selector_opt": a.selector_opt.state_dict(), "history": a.history.state_dict(),
                 "replay": {name: torch.from_numpy(v[: a.replay.size].copy()) for name, v in a.replay.fields.items()},
                 "replay_next": a.replay.next, "coverage": self.coverage.state_dict(),
                 "task": self.task.state_dict() if self.task is not None else {}}
        save_checkpoint(state, path)

    def restore(self, path) -> bool:
        """Resume either phase; task-policy behaviour copies are not saved, so batches of versions
        published before the restart are dropped ('unknown_policy')."""
        saved = load_checkpoint(path)
        if saved is None:
            return False
        a = self.agent
        for name in ("q", "q_target", "q_opt", "disc", "disc_opt", "selector", "selector_opt"):
            getattr(a, name).load_state_dict(saved[name])
        a.history.load_state_dict(saved["history"])
        size = len(saved["replay"]["action"])
        for name, value in saved["replay"].items():
            a.replay.fields[name][:size] = value.numpy()
        a.replay.size, a.replay.next, a.updates = size, int(saved["replay_next"]), int(saved["agent_updates"])
        a.replay.restore_links()
        self.coverage.load_state_dict(saved["coverage"])
        for name in ("version", "updates", "task_updates", "pretrain_steps", "task_steps"):
            setattr(self, name, int(saved[name]))
        if saved["phase"] == "task":
            self.phase = "task"
            self.task = task_agent(self._policy_config(), self.cfg.ppo(), seed=self.cfg.seed)
            self.task.load_state_dict(saved["task"])
        return True

    def progress(self) -> dict[str, float]:
        out = {"policy_version": self.version, "phase_task": float(self.phase == "task"), "updates": self.updates,
               "task_updates": self.task_updates, "selector_updates": self.selector_updates,
               "pretrain_steps": self.pretrain_steps, "task_steps": self.task_steps, "env_steps": self.env_steps,
               "targets": len(self.agent.history.targets), "graphs_seen": self.agent.history.seen(),
               "epsilon": self.epsilon, "waiting_for_graphs": len(self.waiting),
               **{f"dropped_{k}": v for k, v in self.dropped.items()}, **self.last_stats}
        for phase in ("pretrain", "task"):
            out[f"coverage_episodes_{phase}"] = self.coverage.episodes[phase]
            out.update({f"coverage_{phase}: {row}": share for row, share in self.coverage.named(phase, self.objects).items()})
        return {k: float(v) for k, v in out.items() if np.isfinite(v)}


def _with_option(batch: TransitionBatch, option: np.ndarray) -> TransitionBatch:
    return replace(batch, option=option)

