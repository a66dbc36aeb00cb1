"""SkiLD's reward-free pre-training loop (Algorithm 7) and the random-skill coverage of Fig. 6.4.

In one process on a list of household envs: the graph selector picks a target every ``L`` steps
(or when an episode ends), the skill policy acts epsilon-greedily, each transition's induced graph
is the env's true local graph pooled to objects (the chapter's ablation "with ground-truth graphs";
``graphs="true"``) or, with ``graphs="pcmi"``, the point-wise CMI graph of a CDL model trained on the
run's own transitions (:class:`LearnedGraphs`, the chapter's estimator); the history, the
discriminator and both policies learn from it.

:func:`coverage` runs a trained agent for ``episodes`` episodes with random skills (a target drawn
uniformly from the history's targets, ``b`` uniform, every ``L`` steps) and counts the share of
episodes that induce each object-level graph row at least once (Fig. 6.4); ``agent=None`` is
uniformly random primitives, for reference.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from causal.cdl import CDLConfig
from causal.cdl_trainer import CDLTrainer
from causal.factored import FactorLayout
from causal.skild import (SkiLDConfig, graph_matches, induced_local_graphs, key_rows, novelty_reward, object_graphs,
                          object_names, row_keys)
from causal.skild_agent import SkillLearnerConfig, SkiLDAgent
from envs.registry import make_env
from proto.settings import doc

GRAPH_SOURCES = ("true", "pcmi")


@dataclass(frozen=True)
class PretrainConfig:
    """What a pre-training run collects, on which env, with which induced graphs."""

    env: str = doc("installing-printer", "household env to pre-train on")
    env_steps: int = doc(100_000, "env steps of reward-free pre-training (all envs together)")
    num_envs: int = doc(16, "envs stepped together (one batched forward pass per step)")
    episode_length: int = doc(0, "steps per episode (0: the env's default)")
    updates_per_step: int = doc(1, "skill-policy updates per batched env step (num_envs transitions)")
    graphs: str = doc("true", "induced graphs from: true (the env's local graphs, the chapter's ablation) or "
                              "pcmi (a CDL model trained on the run's transitions, point-wise CMI >= 0.02)")
    dynamics_updates_per_step: int = doc(1, "pcmi: dynamics-model updates per batched env step")
    dynamics_warmup: int = doc(2_000, "pcmi: transitions before the dynamics model's first update")

    def __post_init__(self) -> None:
        if self.graphs not in GRAPH_SOURCES:
            raise ValueError(f"graphs must be one of {GRAPH_SOURCES}, got {self.graphs!r}")
        if self.env_steps < 1 or self.num_envs < 1 or self.updates_per_step < 0:
            raise ValueError("env_steps and num_envs must be >= 1, updates_per_step >= 0")


class HouseholdBatch:
    """``num`` envs stepped together, reset when an episode ends; states and true local graphs."""

    def __init__(self, env: str, num: int, episode_length: int, seed: int, task: str = "") -> None:
        kwargs: dict[str, Any] = {"episode_length": episode_length} if episode_length else {}
        if task:
            kwargs["task"] = task
        self.envs = [make_env(env, **kwargs) for _ in range(num)]
        spec = self.envs[0].env_spec()
        self.sizes, self.objects = tuple(spec.factor_sizes), tuple(spec.factor_objects)
        self.actions = spec.action_size
        self.seed = seed
        self.episodes = 0
        self.states = np.stack([self._reset(e) for e in self.envs])
        self.episode = np.arange(1, num + 1, dtype=np.int64)
        """each env's running episode (its reset's number, unique in this batch)"""
        self.t = np.zeros(num, np.int64)
        """each env's step index within its running episode"""

    def _reset(self, env: Any) -> np.ndarray:
        self.episodes += 1
        return env.reset(seed=self.seed * 1_000_003 + self.episodes)[0].astype(np.int64)

    def step(self, actions: np.ndarray, only: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(next states, local graphs [B, d, d+1], terminated, ended, states after resets, rewards)``;
        with ``only`` (bool ``[B]``) the other envs stay as they are (no edge, not ended, reward 0)."""
        d = len(self.sizes)
        nxt, graphs = self.states.copy(), np.repeat(np.eye(d, d + 1, dtype=np.uint8)[None], len(self.envs), axis=0)
        terminated, ended, rewards = (np.zeros(len(self.envs), bool), np.zeros(len(self.envs), bool),
                                      np.zeros(len(self.envs)))
        for i, (env, a) in enumerate(zip(self.envs, actions)):
            if only is not None and not only[i]:
                continue
            obs, rewards[i], terminated[i], truncated, info = env.step(int(a))
            nxt[i], graphs[i], ended[i] = obs, info["local_graph"], terminated[i] or truncated
        after = nxt.copy()
        if only is None:
            self.t += 1
        else:
            self.t[only] += 1
        for i in np.flatnonzero(ended):
            after[i] = self._reset(self.envs[i])
            self.episode[i], self.t[i] = self.episodes, 0
        self.states = after
        return nxt, graphs, terminated, ended, after, rewards


def pretrain(run: PretrainConfig, cfg: SkiLDConfig, learner: SkillLearnerConfig, mode: str = "skild",
             seed: int = 0, log: Callable[[dict[str, float]], None] | None = None) -> tuple[SkiLDAgent, HouseholdBatch]:
    """Algorithm 7 for ``run.env_steps`` steps; returns the agent and its envs."""
    torch.manual_seed(seed)
    envs = HouseholdBatch(run.env, run.num_envs, run.episode_length, seed)
    agent = SkiLDAgent(envs.sizes, len(object_names(envs.objects)), envs.actions, cfg, learner, mode, seed)
    skills = _Skills(agent, envs.states)
    learned = LearnedGraphs(envs, run, seed) if run.graphs == "pcmi" else None
    stats: dict[str, float] = {}
    for step in range(run.env_steps // run.num_envs):
        done_steps = step * run.num_envs
        epsilon = max(learner.eps_end, learner.eps_start - (learner.eps_start - learner.eps_end)
                      * done_steps / max(learner.eps_decay_steps, 1))
        states, episode, t = envs.states, envs.episode.copy(), envs.t.copy()
        actions = agent.act(states, skills.factor, skills.row, skills.b, epsilon)
        nxt, graphs, terminated, ended, after, _ = envs.step(actions)
        if learned is not None:
            graphs = learned.step(agent, states, actions, nxt)
        induced = object_graphs(graphs, envs.objects)
        counts = agent.observe(state=states, action=actions, next_state=nxt, terminated=terminated,
                               induced=induced, factor=skills.factor, row=skills.row, b=skills.b,
                               stream=np.arange(run.num_envs), episode=episode, step=t)
        skills.advance(novelty_reward(counts), ended, after)
        if agent.replay.size >= learner.learning_starts:
            for _ in range(run.updates_per_step):
                stats = agent.update()
        stats.update(skills.maybe_update_selector())
        if log is not None and step % 500 == 0:
            log({"env_steps": float(done_steps), "epsilon": epsilon, "targets": float(len(agent.history.targets)),
                 "seen": float(agent.history.seen()), **stats})
    return agent, envs


class LearnedGraphs:
    """Induced graphs from a learned model (the chapter's estimator): CDL's dynamics model trained on
    the skill replay's transitions, an edge where point-wise CMI >= its threshold (0.02 nats), self-edges
    always, and an unchanged attribute given only its self-edge (the authors' rule)."""

    def __init__(self, envs: HouseholdBatch, run: PretrainConfig, seed: int) -> None:
        spec = envs.envs[0].env_spec()
        self.trainer = CDLTrainer(FactorLayout.from_spec(spec), CDLConfig(), seed=seed)
        self.run = run

    def step(self, agent: SkiLDAgent, states: np.ndarray, actions: np.ndarray, nxt: np.ndarray) -> np.ndarray:
        """Train the model on replayed transitions, then the local graphs ``[B, d, d + 1]`` of this step."""
        replay = agent.replay
        if replay.size >= self.run.dynamics_warmup:
            for _ in range(self.run.dynamics_updates_per_step):
                index = agent.rng.integers(0, replay.size, self.trainer.batch_size)
                self.trainer.update(*_tensors(replay.fields["state"][index], replay.fields["action"][index],
                                              replay.fields["next_state"][index]))
        with torch.no_grad():
            scores = self.trainer.model.pointwise_cmi(*_tensors(states, actions, nxt)).numpy()
        return induced_local_graphs(scores, self.trainer.cfg.cmi_threshold, states, nxt)


def _tensors(states: np.ndarray, actions: np.ndarray, nxt: np.ndarray) -> tuple[torch.Tensor, ...]:
    return (torch.as_tensor(states, dtype=torch.float32), torch.as_tensor(actions, dtype=torch.float32)[:, None],
            torch.as_tensor(nxt, dtype=torch.float32))


class _Skills:
    """The running skill of each env, its remaining steps, and the finished segments' novelty returns."""

    def __init__(self, agent: SkiLDAgent, states: np.ndarray) -> None:
        self.agent = agent
        self.left = np.zeros(len(states), np.int64)
        self.slot, self.factor, self.row, self.b = agent.select(states)
        self.start = states.copy()
        self.left[:] = agent.cfg.skill_steps
        self.returns = np.zeros(len(states))
        self.finished: list[tuple[np.ndarray, int, float]] = []

    def advance(self, novelty: np.ndarray, ended: np.ndarray, states: np.ndarray) -> None:
        self.returns += novelty
        self.left -= 1
        renew = np.flatnonzero((self.left <= 0) | ended)
        if not len(renew):
            return
        for i in renew:
            if self.slot[i] >= 0:
                self.finished.append((self.start[i].copy(), int(self.slot[i]), float(self.returns[i])))
        slot, factor, row, b = self.agent.select(states[renew])
        self.slot[renew], self.factor[renew], self.row[renew], self.b[renew] = slot, factor, row, b
        self.start[renew], self.returns[renew] = states[renew], 0.0
        self.left[renew] = self.agent.cfg.skill_steps

    def maybe_update_selector(self) -> dict[str, float]:
        if len(self.finished) < self.agent.learner.selector_batch:
            return {}
        starts, slots, returns = zip(*self.finished)
        self.finished = []
        return self.agent.update_selector(self.agent.features(np.stack(starts)), np.array(slots), np.array(returns))


def coverage(agent: SkiLDAgent | None, env: str, episodes: int, episode_length: int, seed: int,
             skill_steps: int = 20, num_envs: int = 20, epsilon: float = 0.05,
             hits: dict[str, int] | None = None) -> dict[tuple[int, int], float]:
    """Share of ``episodes`` that induce each ``(factor, row key)`` at least once, under random skills
    (greedy skill policy with ``epsilon``) or, with ``agent=None``, random primitives. ``hits``, if
    given, receives ``segments`` (skills run with a target) and ``induced`` (those that induced it)."""
    envs = HouseholdBatch(env, num_envs, episode_length, seed)
    n = len(object_names(envs.objects))
    rng = np.random.default_rng(seed)
    seen: list[set[tuple[int, int]]] = [set() for _ in range(num_envs)]
    finished: list[set[tuple[int, int]]] = []
    skills = agent.select(envs.states, uniform=True) if agent else None
    left = np.full(num_envs, skill_steps)
    reached = np.zeros(num_envs, bool)
    tally = {"segments": 0, "induced": 0}
    while len(finished) < episodes:
        states = envs.states
        if agent is None:
            actions = rng.integers(0, envs.actions, num_envs)
        else:
            actions = agent.act(states, skills[1], skills[2], skills[3], epsilon)
        _, graphs, _, ended, after, _ = envs.step(actions)
        induced = object_graphs(graphs, envs.objects)
        keys = row_keys(induced)
        for i in range(num_envs):
            seen[i].update(zip(range(n), keys[i].tolist()))
        if agent is not None:
            reached |= graph_matches(induced, skills[1], skills[2])
        left -= 1
        renew = np.flatnonzero((left <= 0) | ended)
        if agent is not None and len(renew):
            targeted = renew[skills[0][renew] >= 0]
            tally["segments"] += len(targeted)
            tally["induced"] += int(reached[targeted].sum())
            reached[renew] = False
            fresh = agent.select(after[renew], uniform=True)
            for part, new in zip(skills, fresh):
                part[renew] = new
        left[renew] = skill_steps
        for i in np.flatnonzero(ended):
            finished.append(seen[i])
            seen[i] = set()
    if hits is not None:
        hits.update(tally)
    counts: dict[tuple[int, int], int] = {}
    for episode in finished[:episodes]:
        for key in episode:
            counts[key] = counts.get(key, 0) + 1
    return {key: c / episodes for key, c in counts.items()}


def target_hit_rates(agent: SkiLDAgent, env: str, segments: int, seed: int, skill_steps: int = 20,
                     num_envs: int = 16, epsilon: float = 0.05, warmup: int = 30) -> list[dict[str, Any]]:
    """Per target of the agent's history: the share of ``skill_steps``-step segments that induce it, run
    by the skill ``(G, b)`` (greedy with ``epsilon``, ``b`` uniform) and by uniformly random actions from
    the *same* start states (copies of the same envs), ``segments`` of each. Start states: each round
    first takes up to ``warmup`` random steps. A segment stops counting once its episode ends.

    Whether a learned skill reaches its target more often than chance is the low level's own test;
    Fig. 6.4's coverage mixes it with how the targets are drawn."""
    envs = HouseholdBatch(env, num_envs, 0, seed)
    rng = np.random.default_rng(seed)
    objects = object_names(envs.objects)
    factors, rows = agent.history.target_arrays(len(objects) + 1)
    out = []
    for t in range(len(factors)):
        factor, row = np.full(num_envs, factors[t]), np.repeat(rows[t][None], num_envs, axis=0)
        hits, total = {"skill": 0, "random": 0}, 0
        while total < segments:
            for _ in range(int(rng.integers(0, warmup + 1))):
                envs.step(rng.integers(0, envs.actions, num_envs))
            start, b = copy.deepcopy(envs), rng.integers(0, agent.k, num_envs)
            for policy in ("skill", "random"):
                run = copy.deepcopy(start)
                alive, got = np.ones(num_envs, bool), np.zeros(num_envs, bool)
                for _ in range(skill_steps):
                    actions = (agent.act(run.states, factor, row, b, epsilon) if policy == "skill"
                               else rng.integers(0, run.actions, num_envs))
                    _, graphs, _, ended, _, _ = run.step(actions)
                    got |= alive & graph_matches(object_graphs(graphs, run.objects), factor, row)
                    alive &= ~ended
                hits[policy] += int(got.sum())
            envs, total = run, total + num_envs
        key = int(row_keys(rows[t][None, None])[0, 0])
        out.append({"target": describe_row(int(factors[t]), key, objects), "segments": total,
                    "skill": hits["skill"] / total, "random": hits["random"] / total})
    return out


def describe_row(factor: int, key: int, objects: tuple[str, ...]) -> str:
    """``"agent, printer, action -> printer"``: a graph row in the words of Fig. 6.4."""
    names = (*objects, "action")
    parents = [names[i] for i in np.flatnonzero(key_rows(np.array(key), len(names)))]
    return f"{', '.join(parents)} -> {objects[factor]}"


def multi_object(factor: int, key: int, width: int) -> bool:
    """Whether a row has a parent object other than the factor itself (an interaction)."""
    parents = np.flatnonzero(key_rows(np.array(key), width))
    return any(p != factor and p != width - 1 for p in parents)


