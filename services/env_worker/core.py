"""env-worker core: an environment and a collection policy that produce TransitionBatches. No bus."""
from __future__ import annotations

import dataclasses
import json
import socket
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from envs.registry import EnvEntry, env_entry
from proto.messages import WORKER_LIFE_EPISODES, EnvSpec, FrameBatch, TransitionBatch, Weights
from proto.messages import SkillBatch
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.episodes import EpisodeStats
from services.env_worker.frames import FrameRecorder
from services.runtime.accept import VersionGate, check_tensor_shapes

if TYPE_CHECKING:
    from causal.rl.policy_weights import Agent


class RandomPolicy:
    """Uniformly random actions (the chapter's collection policy for Chemical)."""

    version = 0
    over_skills = False

    def __init__(self, action_space, seed: int) -> None:
        self.space = action_space
        self.space.seed(seed)

    def reset(self) -> None:
        pass

    def act(self, observation: np.ndarray) -> np.ndarray:
        return np.atleast_1d(np.asarray(self.space.sample(), dtype=np.float32))


def default_policy(entry: EnvEntry, action_space, seed: int):
    """The collection policy before (or without) learned weights: uniformly random actions, except
    where the env's registry entry asks for its skills picked uniformly (the manipulation scene, where
    random motor noise never reaches the cube and the chapter follows Nasiriany et al. with skills
    (reach, grasp, push) picked uniformly with uniform parameters)."""
    runner = entry.skill_runner()
    if runner is not None and entry.skill_collection:
        return runner(action_space, seed)
    return RandomPolicy(action_space, seed)


class PolicyActor:
    """Acts with the newest policy weights loaded; ``version`` is theirs (0: none loaded yet).

    A policy over skills (its config names ``options``) picks the next skill whenever one ends and a
    :class:`~envs.skills.SkillPolicy` runs it; loading newer weights keeps the running skill.
    torch is imported with the first weights, so a worker that never follows a policy starts fast."""

    def __init__(self, obs_dim: int, seed: int, action_space=None, skill_runner: type | None = None,
                 known_version: int = 0) -> None:
        """``known_version``: a policy version known published when this worker started (the bound of
        the first version it takes, :class:`~services.runtime.accept.VersionGate`)."""
        self.obs_dim, self.seed, self.action_space, self.skill_runner = obs_dim, seed, action_space, skill_runner
        self.agent: Agent | None = None
        self.skills = None
        self.config_json = ""
        self.version = 0
        self.versions = VersionGate(known=known_version)

    def load(self, weights: Weights) -> bool:
        """Take ``weights`` if newer than the current ones (ValueError if they do not fit this env;
        ProtocolError if their version jumps past the bound)."""
        if weights.version <= self.version or not self.versions.newer("policy", weights.version):
            return False
        from causal.rl.policy_weights import agent_from_config_json, import_policy, policy_options

        agent, skills = self.agent, self.skills
        if weights.config_json != self.config_json:
            check_tensor_shapes(lambda: self._shapes(weights.config_json), weights.tensors, "the policy configuration")
            agent = agent_from_config_json(weights.config_json, self.seed, self.obs_dim)
            skills = self._skill_runner(policy_options(weights.config_json))
        import_policy(agent, weights.tensors)
        self.versions.accept("policy", weights.version)
        self.agent, self.skills, self.config_json, self.version = agent, skills, weights.config_json, weights.version
        return True

    def _shapes(self, config_json: str) -> dict[str, tuple[int, ...]]:
        """Names and shapes of the tensors a policy of ``config_json`` publishes."""
        from causal.rl.policy_weights import acting_module, agent_from_config_json

        module = acting_module(agent_from_config_json(config_json, self.seed, self.obs_dim))
        return {name: tuple(t.shape) for name, t in module.state_dict().items()}

    def _skill_runner(self, options: tuple[str, ...]):
        if not options:
            return None
        if self.skill_runner is None:
            raise ValueError("a policy over skills for an env without skills")
        if options != self.skill_runner.OPTION_NAMES:
            raise ValueError(f"a policy over skills {list(options)}; this worker runs "
                             f"{list(self.skill_runner.OPTION_NAMES)}")
        if self.skills is not None:
            return self.skills
        return self.skill_runner(self.action_space, self.seed, chooser=self._choose)

    def _choose(self, observation: np.ndarray) -> int:
        return int(np.asarray(self.agent.act(observation)).reshape(-1)[0])

    @property
    def over_skills(self) -> bool:
        return self.skills is not None

    @property
    def last_option(self) -> int:
        return self.skills.last_option if self.skills is not None else -1

    def reset(self) -> None:
        if self.skills is not None:
            self.skills.reset()

    def act(self, observation: np.ndarray) -> np.ndarray:
        if self.skills is not None:
            return self.skills.act(observation)
        return np.atleast_1d(np.asarray(self.agent.act(observation), dtype=np.float32))


GENERATION_SEED_STRIDE = 1_000_003
"""Seed offset per restart of a worker (a prime far above any worker index)."""
GENERATION_EPISODES = WORKER_LIFE_EPISODES
"""Episode ids of restart k start at k x this (ids stay unique per worker id across restarts)."""


def next_generation(path: Path) -> int:
    """The number of earlier starts recorded at ``path`` (a small JSON file), recording this one."""
    try:
        starts = int(json.loads(path.read_text())["starts"])
    except (OSError, ValueError, KeyError, TypeError):
        starts = 0
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"starts": starts + 1}))
    tmp.replace(path)
    return starts


def resolve_worker_index(cfg: EnvWorkerConfig) -> EnvWorkerConfig:
    """Replicas started from one configuration (``docker compose --scale``) take distinct indices
    from their hostnames, so their seeds, worker ids and instance ids differ."""
    if cfg.worker_index >= 0:
        return cfg
    host = socket.gethostname()
    return dataclasses.replace(cfg, worker_index=zlib.crc32(host.encode()) % 100_000, instance=host)


def with_declared_bounds(spec: EnvSpec, space: Any) -> EnvSpec:
    """``spec`` carrying the observation space's bounds (``state_low``/``state_high``) where the space is a
    Box of the state's width (an infinite bound as float32's largest value): consumers then refuse
    transitions outside them. Other spaces declare no bounds."""
    low, high = getattr(space, "low", None), getattr(space, "high", None)
    if low is None or high is None or np.shape(low) != (spec.state_dim,) or np.shape(high) != (spec.state_dim,):
        return spec
    big = float(np.finfo(np.float32).max)
    bounds = [np.nan_to_num(np.asarray(b, np.float64), posinf=big, neginf=-big).clip(-big, big).astype(np.float32)
              for b in (low, high)]
    return dataclasses.replace(spec, state_low=bounds[0], state_high=bounds[1])


class EnvWorkerCore:
    """Steps one environment and packs consecutive steps into TransitionBatches."""

    def __init__(self, cfg: EnvWorkerConfig, generation: int = 0) -> None:
        """``generation``: how many times this worker started before in the run (a restart); each
        generation draws new seeds and new episode ids, so a restarted worker repeats no data."""
        cfg = resolve_worker_index(cfg)
        self.cfg = cfg
        self.worker_id = f"w{cfg.worker_index}"
        self.entry = env_entry(cfg.env)
        self.env = self.entry.make(**self.entry.kwargs(cfg.env_options))
        self.spec: EnvSpec = with_declared_bounds(self.env.unwrapped.env_spec(), self.env.observation_space)
        seed = cfg.seed + cfg.worker_index + GENERATION_SEED_STRIDE * generation
        self.random_policy = default_policy(self.entry, self.env.action_space, seed)
        self.actor = PolicyActor(self.spec.state_dim, seed, self.env.action_space, self.entry.skill_runner(),
                                 cfg.known_version)
        self.skild = None
        if cfg.skild:
            from causal.skild_policy import SkildActor

            self.skild = SkildActor(seed)
            """SkiLD's skill/task policies (``cfg.skild``): the only collection policy, once loaded."""
        self.observation, info = self.env.reset(seed=seed)
        self.recorder = (FrameRecorder(info, cfg.frame_stride, labels=cfg.publish_frames)
                         if cfg.publish_frames or cfg.frames_beside else None)
        self.episodes = EpisodeStats(len(getattr(self.env.unwrapped, "stage_names", ())))
        self.first_episode = GENERATION_EPISODES * generation
        self.episode, self.step_in_episode = self.first_episode, 0
        self.env_steps, self.seq = 0, 0

    @property
    def episodes_finished(self) -> int:
        """Episodes this process finished: a count from 0, not the episode id (which a restarted
        worker's generation offsets by :data:`GENERATION_EPISODES`)."""
        return self.episode - self.first_episode

    @property
    def option_names(self) -> tuple[str, ...]:
        """Names of the env's skill options (what a batch's ``option`` indexes); () without skills."""
        runner = self.actor.skill_runner
        return tuple(runner.OPTION_NAMES) if runner is not None else ()

    @property
    def policy(self) -> RandomPolicy | PolicyActor:
        """The collection policy: the newest policy weights once any arrived, random before (SkiLD: its
        policies only; :attr:`waiting` until they arrive)."""
        if self.skild is not None:
            return self.skild
        return self.actor if self.actor.version > 0 else self.random_policy

    @property
    def waiting(self) -> bool:
        """A SkiLD worker before its first policy: it takes no step (every step is a skill's)."""
        return self.skild is not None and self.skild.version == 0

    def apply_weights(self, weights: Weights) -> bool:
        """Act with ``weights`` from the next batch on, if newer (ValueError if they do not fit)."""
        if self.skild is None:
            return self.actor.load(weights)
        from causal.skild_policy import SkildPolicyConfig

        cfg = SkildPolicyConfig.from_json(weights.config_json)
        if cfg.sizes != tuple(self.spec.factor_sizes) or cfg.actions != self.spec.action_size:
            raise ValueError(f"a SkiLD policy for factor sizes {cfg.sizes} and {cfg.actions} actions; this env has "
                             f"{tuple(self.spec.factor_sizes)} and {self.spec.action_size}")
        phase = self.skild.phase
        loaded = self.skild.load(weights.version, weights.config_json, weights.tensors)
        if loaded and phase and self.skild.phase != phase:
            self.episodes = EpisodeStats(self.episodes.num_stages)  # task metrics from the task phase only
        return loaded

    def skill_batch(self, batch: TransitionBatch) -> SkillBatch:
        """A SkiLD worker's ``batch`` (just collected) with the skill each of its steps ran."""
        slot, b, started = self.skild.take_labels()
        if len(slot) != len(batch):
            raise RuntimeError(f"{len(slot)} skill labels for a batch of {len(batch)} steps")
        return SkillBatch(transitions=batch, phase=self.skild.phase, slot=slot, b=b, started=started)

    def collect_skills(self, steps: int | None = None) -> SkillBatch:
        """A SkiLD worker's batch: the transitions and the skill each step ran."""
        return self.skill_batch(self.collect(steps))

    def collect(self, steps: int | None = None) -> TransitionBatch:
        """Step the environment ``steps`` times (resetting at episode ends) and return the batch."""
        steps = steps or self.cfg.batch_steps
        d, a = self.spec.state_dim, self.spec.action_dim
        state, next_state = np.empty((steps, d), np.float32), np.empty((steps, d), np.float32)
        action, reward = np.empty((steps, a), np.float32), np.empty(steps, np.float32)
        terminated, truncated = np.zeros(steps, bool), np.zeros(steps, bool)
        episode, step = np.empty(steps, np.int64), np.empty(steps, np.int32)
        graphs = np.empty((steps, self.spec.num_factors, self.spec.num_factors + 1), np.uint8) if self.cfg.local_graphs else None
        policy = self.policy
        option = np.full(steps, -1, np.int32) if policy.over_skills else None
        if self.recorder is not None:
            self.recorder.begin()
        for t in range(steps):
            act = policy.act(self.observation)
            if option is not None:
                option[t] = policy.last_option
            env_action = int(act[0]) if self.spec.action_kind == "categorical" else act
            obs, r, term, trunc, info = self.env.step(env_action)
            state[t], action[t], reward[t], next_state[t] = self.observation, act, r, obs
            terminated[t], truncated[t], episode[t], step[t] = term, trunc, self.episode, self.step_in_episode
            if graphs is not None:
                graphs[t] = info["local_graph"]
            self.step_in_episode += 1
            self.observation = obs
            self.episodes.step(r, info, term or trunc)
            reset_info = None
            if term or trunc:
                policy.reset()  # a policy over skills starts the next episode with a fresh decision
                self.observation, reset_info = self.env.reset()
                self.episode, self.step_in_episode = self.episode + 1, 0
            if self.recorder is not None:
                self.recorder.record(info, reset_info)
        self.env_steps += steps
        batch = TransitionBatch(worker_id=self.worker_id, seq=self.seq, policy_version=policy.version,
                                state=state, action=action, reward=reward, next_state=next_state,
                                terminated=terminated, truncated=truncated, episode_id=episode, step=step,
                                local_graph=graphs, option=option)
        self.seq += 1
        return batch

    def collect_frames(self, steps: int | None = None) -> FrameBatch:
        """As :meth:`collect`, the steps as frames (``publish_frames``): a FrameBatch for the factor-extractor."""
        return self.frames_of(self.collect(steps))

    def frames_of(self, batch: TransitionBatch) -> FrameBatch:
        """The frames of ``batch``, the batch :meth:`collect` returned last (``publish_frames`` or
        ``frames_beside``)."""
        if self.recorder is None:
            raise RuntimeError("this worker does not record frames (publish_frames and frames_beside are off)")
        return self.recorder.pack(batch)
