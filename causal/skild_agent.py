"""SkiLD's learners (ch. 6.2.2-6.2.3): the factorised skill policy and the graph-selection policy.

- :class:`SkillQNetwork`: the low level. The authors train one Rainbow DQN per factor; we train one
  double DQN with a shared trunk and **one Q-head per factor** (the chapter's factorised low level:
  the target's factor picks the head), inputs the state's one-hots, the target ``G`` (factor one-hot
  and row bits) and ``b`` (one-hot). A Q-learner, because hindsight relabelling needs an off-policy
  learner (a relabelled sample was collected under another skill); plain double DQN with
  epsilon-greedy, because Rainbow's extras (distributional atoms, noisy nets, prioritised n-step
  replay) cost CPU time the runs here do not have, and none of them is what SkiLD is about.
- :class:`GraphSelector`: the high level. A masked categorical policy over the target slots of the
  :class:`~causal.skild.GraphHistory` with a value baseline, updated by one-step policy gradient on
  eq. 6.1's novelty summed over the ``L`` steps of the skill it picked (the authors: masked PPO
  across decisions).
- :class:`SkiLDAgent`: both, the discriminator and the replay, with the update of Algorithm 7
  (lines 13-19). ``mode="diayn"`` is the DIAYN baseline on the same machinery: no graph (one fixed
  empty target), reward ``log q(b | s') + log K``, no relabelling.

One thread, batched tensors; the collection loop is :mod:`causal.skild_pretrain`.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from causal.skild import (DiversityDiscriminator, GraphHistory, SkiLDConfig, graph_matches, hindsight_relabel,
                          skill_reward, target_features)
from proto.settings import doc

MODES = ("skild", "diayn")


@dataclass(frozen=True)
class SkillLearnerConfig:
    """The low-level DQN, the high-level selector and their budgets (pre-training, ch. 6.2)."""

    gamma: float = doc(0.9, "discount of the skill policy (the authors' Rainbow: 0.9)")
    lr: float = doc(5e-4, "Adam learning rate of the skill Q-network")
    hidden: int = doc(128, "hidden width of the skill Q-network's trunk (two layers)")
    batch_size: int = doc(128, "replayed transitions per update")
    replay_capacity: int = doc(200_000, "transitions the skill replay holds")
    target_every: int = doc(250, "updates between copies of the online Q-network to the target one")
    learning_starts: int = doc(2_000, "transitions collected before the first update")
    eps_start: float = doc(1.0, "epsilon-greedy exploration at the start")
    eps_end: float = doc(0.05, "epsilon-greedy exploration after eps_decay_steps")
    eps_decay_steps: int = doc(40_000, "env steps over which epsilon decays linearly")
    selector_lr: float = doc(1e-3, "Adam learning rate of the graph-selection policy")
    selector_entropy: float = doc(0.01, "entropy bonus of the graph-selection policy")
    selector_batch: int = doc(64, "finished skill segments per graph-selection update")
    diayn_k: int = doc(8, "skills of the DIAYN baseline (mode diayn)")
    n_step: int = doc(1, "steps of reward summed before bootstrapping (the authors' Rainbow: 3); the later "
                         "steps are paid for the replayed sample's skill, without an off-policy correction")
    end_on_target: bool = doc(False, "a step that induces the skill's target ends its return (no bootstrap past "
                                     "it): the Q-values then measure how soon the target is reached")

    def __post_init__(self) -> None:
        if self.n_step < 1:
            raise ValueError(f"n_step must be >= 1, got {self.n_step}")


def one_hot_states(states: np.ndarray, sizes: tuple[int, ...]) -> torch.Tensor:
    """Categorical states ``[B, d_S]`` (category indices) -> concatenated one-hots ``[B, sum(sizes)]``."""
    offsets = torch.as_tensor(np.concatenate([[0], np.cumsum(sizes)[:-1]]), dtype=torch.long)
    index = torch.as_tensor(np.asarray(states), dtype=torch.long) + offsets
    out = torch.zeros(index.shape[0], int(sum(sizes)))
    return out.scatter_(1, index, 1.0)


class SkillQNetwork(nn.Module):
    """``Q(s, G, b, .)``: a shared trunk, one head of ``|A|`` values per factor (the target's picks it)."""

    def __init__(self, state_features: int, num_factors: int, k: int, actions: int, hidden: int) -> None:
        super().__init__()
        self.num_factors, self.k, self.actions = num_factors, k, actions
        self.trunk = nn.Sequential(nn.Linear(state_features + 2 * num_factors + 1 + k, hidden), nn.ReLU(),
                                   nn.Linear(hidden, hidden), nn.ReLU())
        self.heads = nn.Linear(hidden, num_factors * actions)

    def forward(self, features: torch.Tensor, factor: torch.Tensor, row: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        x = torch.cat([features, target_features(factor, row, self.num_factors), F.one_hot(b, self.k).float()], 1)
        q = self.heads(self.trunk(x)).view(-1, self.num_factors, self.actions)
        return q[torch.arange(len(factor)), factor]


class GraphSelector(nn.Module):
    """``pi_G(slot | s)`` over the history's target slots (the slots not yet filled masked), and ``V(s)``."""

    def __init__(self, state_features: int, slots: int, hidden: int = 64) -> None:
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(state_features, hidden), nn.ReLU())
        self.logits, self.value = nn.Linear(hidden, slots), nn.Linear(hidden, 1)

    def forward(self, features: torch.Tensor, filled: int) -> tuple[torch.distributions.Categorical, torch.Tensor]:
        h = self.trunk(features)
        logits = self.logits(h)
        logits[:, filled:] = -1e9
        return torch.distributions.Categorical(logits=logits), self.value(h).squeeze(1)


class SkillReplay:
    """A ring of skill transitions with their induced (object-level) graphs and skill labels.

    Rows added with their ``stream`` (an env or worker), ``episode`` and ``step`` are linked to the
    next step of the same episode (``successor``), so :meth:`future` can find the later steps that
    hindsight relabelling draws targets from (HER's "future" strategy). A row the ring overwrites
    loses its link, and a link is followed only where the row it leads to holds the same episode's
    next step."""

    def __init__(self, capacity: int, state_dim: int, num_factors: int) -> None:
        n = num_factors
        self.capacity, self.size, self.next = capacity, 0, 0
        self.fields = {
            "state": np.zeros((capacity, state_dim), np.int16), "action": np.zeros(capacity, np.int64),
            "next_state": np.zeros((capacity, state_dim), np.int16), "terminated": np.zeros(capacity, bool),
            "induced": np.zeros((capacity, n, n + 1), bool), "factor": np.zeros(capacity, np.int64),
            "row": np.zeros((capacity, n + 1), bool), "b": np.zeros(capacity, np.int64),
            "counts": np.zeros((capacity, n), np.int64),
            "stream": np.full(capacity, -1, np.int64), "episode": np.full(capacity, -1, np.int64),
            "step": np.full(capacity, -1, np.int64), "successor": np.full(capacity, -1, np.int64),
        }
        self._last: dict[int, int] = {}

    def add(self, stream: np.ndarray | None = None, episode: np.ndarray | None = None, step: np.ndarray | None = None,
            **rows: np.ndarray) -> None:
        """Append rows; with ``stream``, ``episode`` and ``step`` (each ``[B]``, rows of one stream in
        step order) each row is linked as its episode's previous step's successor."""
        count = len(rows["action"])
        index = (self.next + np.arange(count)) % self.capacity
        for name, value in rows.items():
            self.fields[name][index] = value
        f = self.fields
        f["successor"][index] = -1
        if stream is None or episode is None or step is None:
            f["stream"][index] = f["episode"][index] = f["step"][index] = -1
        else:
            f["stream"][index], f["episode"][index], f["step"][index] = stream, episode, step
            for position, key in zip(index.tolist(), np.asarray(stream).tolist()):
                last = self._last.get(key)
                if last is not None and self.follows(last, position):
                    f["successor"][last] = position
                self._last[key] = position
        self.next = (self.next + count) % self.capacity
        self.size = min(self.size + count, self.capacity)

    def restore_links(self) -> None:
        """After the fields were loaded (a checkpoint): each stream's newest row again takes the next
        row added for that stream as its successor, so episodes running across a restart stay linked."""
        order = np.arange(self.size) if self.size < self.capacity else (self.next + np.arange(self.size)) % self.capacity
        streams = self.fields["stream"][order][::-1]
        keys, first = np.unique(streams, return_index=True)
        newest = order[::-1][first]
        self._last = {int(k): int(p) for k, p in zip(keys, newest) if k >= 0}

    def follows(self, before: np.ndarray | int, after: np.ndarray | int) -> np.ndarray:
        """Whether row ``after`` holds the step right after row ``before``'s, in the same episode."""
        f = self.fields
        return ((f["stream"][after] == f["stream"][before]) & (f["stream"][after] >= 0)
                & (f["episode"][after] == f["episode"][before]) & (f["step"][after] == f["step"][before] + 1))

    def sample_index(self, batch: int, rng: np.random.Generator) -> np.ndarray:
        return rng.integers(0, self.size, batch)

    def rows(self, index: np.ndarray, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
        """The fields (or only ``names``) of rows ``index``."""
        return {name: self.fields[name][index] for name in (names or self.fields)}

    def sample(self, batch: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        return self.rows(self.sample_index(batch, rng))

    def future(self, index: np.ndarray, horizon: int, rng: np.random.Generator) -> np.ndarray:
        """For each row, a row ``m`` steps later in its episode, ``m`` uniform in ``[0, horizon)``,
        or the episode's last linked step if it ends (or the ring lost it) sooner."""
        index = np.asarray(index)
        hops = rng.integers(0, horizon, len(index))
        at = index.copy()
        successor = self.fields["successor"]
        for k in range(horizon - 1):
            go = hops > k
            if not go.any():
                break
            nxt = successor[at]
            ok = go & (nxt >= 0)
            ok[ok] = self.follows(at[ok], nxt[ok])
            at = np.where(ok, nxt, at)
        return at


class SkiLDAgent:
    """The skill policy, the graph selector, the discriminator and the graph history of one run."""

    def __init__(self, sizes: tuple[int, ...], num_factors: int, actions: int, cfg: SkiLDConfig,
                 learner: SkillLearnerConfig, mode: str = "skild", seed: int = 0) -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        torch.manual_seed(seed)
        self.sizes, self.n, self.actions, self.cfg, self.learner, self.mode = sizes, num_factors, actions, cfg, learner, mode
        self.k = cfg.diversity_k if mode == "skild" else learner.diayn_k
        self.rng = np.random.default_rng(seed)
        features = int(sum(sizes))
        self.q = SkillQNetwork(features, num_factors, self.k, actions, learner.hidden)
        self.q_target = copy.deepcopy(self.q)
        self.q_opt = torch.optim.Adam(self.q.parameters(), lr=learner.lr)
        self.disc = DiversityDiscriminator(features, num_factors, self.k, cfg.discriminator_hidden)
        self.disc_opt = torch.optim.Adam(self.disc.parameters(), lr=cfg.discriminator_lr)
        self.selector = GraphSelector(features, cfg.max_targets)
        self.selector_opt = torch.optim.Adam(self.selector.parameters(), lr=learner.selector_lr)
        self.history = GraphHistory(num_factors, cfg.eligible_after, cfg.max_targets)
        self.replay = SkillReplay(learner.replay_capacity, len(sizes), num_factors)
        self.updates = 0

    def features(self, states: np.ndarray) -> torch.Tensor:
        return one_hot_states(states, self.sizes)

    # ---------------------------------------------------------------- acting

    def act(self, states: np.ndarray, factor: np.ndarray, row: np.ndarray, b: np.ndarray, epsilon: float) -> np.ndarray:
        """Epsilon-greedy primitive actions of the skills ``(G, b)`` per env."""
        with torch.no_grad():
            q = self.q(self.features(states), torch.as_tensor(factor), torch.as_tensor(row), torch.as_tensor(b))
        greedy = q.argmax(1).numpy()
        explore = self.rng.random(len(greedy)) < epsilon
        return np.where(explore, self.rng.integers(0, self.actions, len(greedy)), greedy)

    def select(self, states: np.ndarray, uniform: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """New skills for these envs: ``(slot, factor, row, b)``; ``slot`` -1 while no target is eligible
        (and in DIAYN mode: one empty target). ``uniform``: targets uniformly (random skills)."""
        count = len(states)
        b = self.rng.integers(0, self.k, count)
        filled = len(self.history.targets)
        if self.mode == "diayn" or filled == 0:
            return np.full(count, -1), np.zeros(count, np.int64), np.zeros((count, self.n + 1), bool), b
        if uniform:
            slot = self.rng.integers(0, filled, count)
        else:
            with torch.no_grad():
                dist, _ = self.selector(self.features(states), filled)
                slot = dist.sample().numpy()
        factors, rows = self.history.target_arrays(self.n + 1)
        return slot, factors[slot], rows[slot], b

    # ---------------------------------------------------------------- learning

    def observe(self, stream: np.ndarray | None = None, episode: np.ndarray | None = None,
                step: np.ndarray | None = None, **rows: np.ndarray) -> np.ndarray:
        """Record transitions (``state, action, next_state, terminated, induced, factor, row, b``;
        with ``stream``, ``episode`` and ``step`` they are linked for hindsight's later steps);
        update the graph history; return each transition's novelty counts ``[B, N]`` (after the update)."""
        if self.mode == "skild":
            self.history.update(rows["induced"])
        counts = self.history.counts(rows["induced"])
        self.replay.add(stream=stream, episode=episode, step=step, counts=counts, **rows)
        return counts

    def rewards(self, batch: dict[str, np.ndarray], features: torch.Tensor,
                achieved: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
        """Hindsight-relabelled labels, their log q and eq. 6.2's reward (DIAYN: ``log q + log K``).
        ``achieved``: the rows new targets are drawn from (a later step of each sample's episode);
        by default the samples' own."""
        factor, row = batch["factor"], batch["row"]
        if self.mode == "skild":
            source = batch if achieved is None else achieved
            factor, row, _ = hindsight_relabel(source["induced"], factor, row, source["counts"],
                                               self.cfg.relabel_fraction, self.rng)
            if self.cfg.relabel_random > 0 and len(self.history.targets):
                factor, row = self._random_targets(factor, row)
        reward, log_q = self.step_reward(batch, features, factor, row)
        return reward, {"factor": factor, "row": row}, log_q

    def _random_targets(self, factor: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``relabel_random`` of the samples get a target drawn uniformly from the history's."""
        drawn = self.rng.random(len(factor)) < self.cfg.relabel_random
        factors, rows = self.history.target_arrays(self.n + 1)
        pick = self.rng.integers(0, len(factors), len(factor))
        return (np.where(drawn, factors[pick], factor).astype(np.int64),
                np.where(drawn[:, None], rows[pick], row))

    def step_reward(self, rows: dict[str, np.ndarray], features: torch.Tensor, factor: np.ndarray,
                    row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 6.2's reward of replayed steps under the skills ``(factor, row, rows["b"])`` (DIAYN:
        ``log q + log K``), and ``log q(b | s', G)``; ``features`` are the steps' next states'."""
        with torch.no_grad():
            log_q = self.disc.log_prob(features, torch.as_tensor(factor), torch.as_tensor(row),
                                       torch.as_tensor(rows["b"])).numpy()
        if self.mode == "diayn":
            return (log_q + math.log(self.k)).astype(np.float32), log_q
        return skill_reward(rows["induced"], factor, row, log_q, self.cfg.diversity_weight), log_q

    def update(self) -> dict[str, float]:
        """One step of Algorithm 7's lines 13-19 on a replayed batch (discriminator, then skill Q)."""
        index = self.replay.sample_index(self.learner.batch_size, self.rng)
        batch = self.replay.rows(index)
        achieved = None
        if self.mode == "skild" and self.cfg.relabel_horizon > 1:
            achieved = self.replay.rows(self.replay.future(index, self.cfg.relabel_horizon, self.rng),
                                        ("induced", "counts"))
        s, s2 = self.features(batch["state"]), self.features(batch["next_state"])
        reward, labels, _ = self.rewards(batch, s2, achieved)
        factor, row, b = (torch.as_tensor(labels["factor"]), torch.as_tensor(labels["row"]),
                          torch.as_tensor(batch["b"]))
        disc_loss = self._update_discriminator(s2, factor, row, b, batch, labels)
        ret, last, discount = self._n_step(index, batch, reward, labels)
        with torch.no_grad():
            s_n = s2 if self.learner.n_step == 1 else self.features(self.replay.fields["next_state"][last])
            best = self.q(s_n, factor, row, b).argmax(1, keepdim=True)
            bootstrap = self.q_target(s_n, factor, row, b).gather(1, best).squeeze(1)
            target = torch.as_tensor(ret) + torch.as_tensor(discount) * bootstrap
        q = self.q(s, factor, row, b).gather(1, torch.as_tensor(batch["action"])[:, None]).squeeze(1)
        loss = F.smooth_l1_loss(q, target)
        self.q_opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.q.parameters(), 10.0)
        self.q_opt.step()
        self.updates += 1
        if self.updates % self.learner.target_every == 0:
            self.q_target.load_state_dict(self.q.state_dict())
        return {"q_loss": float(loss.detach()), "disc_loss": disc_loss, "reward": float(reward.mean())}

    def _n_step(self, index: np.ndarray, batch: dict[str, np.ndarray], reward: np.ndarray,
                labels: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ``n_step`` return of each replayed sample under its (relabelled) skill: its reward and
        those of the next ``n - 1`` steps of its episode, each paid by eq. 6.2 for this sample's
        skill (as the authors' Rainbow, without an off-policy correction for the later steps' actions).
        It stops early where the episode terminates (no bootstrap) or its next step is not in the
        replay (bootstrap there). Returns ``(return, row whose next state bootstraps, discount)``."""
        gamma = self.learner.gamma
        ret = reward.astype(np.float64)
        last = np.asarray(index).copy()
        alive = ~batch["terminated"] & ~self._ends(batch, labels["factor"], labels["row"])
        discount = gamma * alive
        successor = self.replay.fields["successor"]
        for _ in range(self.learner.n_step - 1):
            nxt = successor[last]
            go = alive & (nxt >= 0)
            go[go] = self.replay.follows(last[go], nxt[go])
            if not go.any():
                break
            rows = self.replay.rows(nxt[go], ("induced", "next_state", "terminated", "b"))
            r, _ = self.step_reward(rows, self.features(rows["next_state"]), labels["factor"][go], labels["row"][go])
            ret[go] += discount[go] * r
            last[go] = nxt[go]
            alive[go] = ~rows["terminated"] & ~self._ends(rows, labels["factor"][go], labels["row"][go])
            discount[go] *= gamma * alive[go]
        return ret.astype(np.float32), last, discount.astype(np.float32)

    def _ends(self, rows: dict[str, np.ndarray], factor: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Steps where the skill's return ends on its target (``end_on_target``, SkiLD only)."""
        if self.mode != "skild" or not self.learner.end_on_target:
            return np.zeros(len(factor), bool)
        return graph_matches(rows["induced"], factor, row)

    def _update_discriminator(self, s2: torch.Tensor, factor: torch.Tensor, row: torch.Tensor, b: torch.Tensor,
                              batch: dict[str, np.ndarray], labels: dict[str, np.ndarray]) -> float:
        """Cross-entropy of ``b`` on the states where the (relabelled) target was induced."""
        if self.mode == "skild":
            keep = torch.as_tensor(graph_matches(batch["induced"], labels["factor"], labels["row"]))
            if not keep.any():
                return float("nan")
            s2, factor, row, b = s2[keep], factor[keep], row[keep], b[keep]
        loss = self.disc.loss(s2, factor, row, b)
        self.disc_opt.zero_grad()
        loss.backward()
        self.disc_opt.step()
        return float(loss.detach())

    def update_selector(self, features: torch.Tensor, slots: np.ndarray, returns: np.ndarray) -> dict[str, float]:
        """One policy-gradient step of the graph selector on finished skill segments (eq. 6.1 returns)."""
        dist, value = self.selector(features, len(self.history.targets))
        ret = torch.as_tensor(returns, dtype=torch.float32)
        advantage = ret - value.detach()
        logp = dist.log_prob(torch.as_tensor(slots))
        loss = -(advantage * logp).mean() + 0.5 * (value - ret).square().mean() \
            - self.learner.selector_entropy * dist.entropy().mean()
        self.selector_opt.zero_grad()
        loss.backward()
        self.selector_opt.step()
        return {"selector_loss": float(loss.detach()), "selector_return": float(ret.mean())}
