"""SkiLD's policies on the wire (ch. 6): what the policy-learner publishes and an env-worker acts with.

``Weights(model="skild-policy")`` carries the skill Q-network (the low level), the graph selector
(pre-training's high level) and, once fine-tuning started, the task policy (a PPO actor-critic over
the options ``slot * K + b``), and a config naming the phase, the history's targets (``(factor, row
key)`` per slot, append-only), the skill length ``L`` and the exploration rate. Pure (no bus).

:class:`SkildActor` steps one env: it picks a skill at an episode's start and every ``L`` steps (the
selector in ``pretrain``, a uniform ``b``; the task policy in ``task``), acts epsilon-greedily (greedy
in ``task``: the low level is frozen) with the Q-network, and records each step's skill labels for
the worker's :class:`~proto.messages.SkillBatch`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from causal.rl import ActionSpec, PPOAgent, PPOConfig
from causal.skild import key_rows
from causal.skild_agent import GraphSelector, SkillQNetwork, one_hot_states

MODEL = "skild-policy"
"""The weights topic segment of SkiLD's policies (``weights/skild-policy``)."""
PARTS = ("q", "selector", "task")


@dataclass(frozen=True)
class SkildPolicyConfig:
    """The architecture and state of a published SkiLD policy (its ``config_json``)."""

    phase: str
    sizes: tuple[int, ...]
    num_factors: int
    actions: int
    k: int
    hidden: int
    selector_slots: int
    skill_steps: int
    epsilon: float
    targets: tuple[tuple[int, int], ...]
    task_hidden: tuple[int, ...] = (64, 64)

    @property
    def options(self) -> int:
        """The task policy's actions: every target times every ``b`` (at least one target slot)."""
        return max(len(self.targets), 1) * self.k

    def to_json(self) -> str:
        data = {"model": MODEL, **{k: getattr(self, k) for k in self.__dataclass_fields__}}
        data["targets"] = [list(t) for t in self.targets]
        return json.dumps(data, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "SkildPolicyConfig":
        """ValueError for a config that is not SkiLD's policy."""
        data = json.loads(text)
        if data.get("model") != MODEL:
            raise ValueError(f"not a SkiLD policy config: {data.get('model')!r}")
        data.pop("model")
        try:
            return cls(**{**data, "sizes": tuple(data["sizes"]), "task_hidden": tuple(data["task_hidden"]),
                          "targets": tuple((int(f), int(k)) for f, k in data["targets"])})
        except (TypeError, KeyError, ValueError) as exc:
            raise ValueError(f"bad SkiLD policy config: {exc}") from None


def task_agent(cfg: SkildPolicyConfig, ppo: PPOConfig | None = None, seed: int = 0) -> PPOAgent:
    """The task policy: PPO over the one-hot state, one categorical action per option."""
    ppo = ppo or PPOConfig(hidden=cfg.task_hidden)
    return PPOAgent(int(sum(cfg.sizes)), ActionSpec("categorical", cfg.options), ppo, seed=seed)


def networks(cfg: SkildPolicyConfig, seed: int = 0) -> dict[str, torch.nn.Module]:
    """Fresh modules of the published architecture: ``q``, ``selector`` and, in ``task``, ``task``."""
    torch.manual_seed(seed)
    features = int(sum(cfg.sizes))
    nets: dict[str, torch.nn.Module] = {
        "q": SkillQNetwork(features, cfg.num_factors, cfg.k, cfg.actions, cfg.hidden),
        "selector": GraphSelector(features, cfg.selector_slots)}
    if cfg.phase == "task":
        nets["task"] = task_agent(cfg, seed=seed).net
    return nets


def export_tensors(nets: dict[str, torch.nn.Module]) -> dict[str, np.ndarray]:
    return {f"{part}.{name}": t.detach().cpu().numpy().copy()
            for part, net in nets.items() for name, t in net.state_dict().items()}


def import_tensors(nets: dict[str, torch.nn.Module], tensors: dict[str, np.ndarray]) -> None:
    """Load ``tensors`` into ``nets`` (ValueError on a missing, extra or misshapen tensor)."""
    parts = {part: {} for part in nets}
    for name, value in tensors.items():
        part, _, rest = name.partition(".")
        if part not in parts:
            raise ValueError(f"SkiLD policy tensor {name!r} of no network")
        parts[part][rest] = torch.from_numpy(np.array(value))
    try:
        for part, net in nets.items():
            net.load_state_dict(parts[part])
    except RuntimeError as exc:
        raise ValueError(f"SkiLD policy tensors do not fit: {exc}") from None


class SkildActor:
    """Acts in one env with the newest SkiLD policy; records the skill of every step."""

    def __init__(self, seed: int) -> None:
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.cfg: SkildPolicyConfig | None = None
        self.nets: dict[str, torch.nn.Module] = {}
        self.version = 0
        self.over_skills = False
        self.left = 0
        self.slot, self.b = -1, 0
        self._labels: list[tuple[int, int, bool]] = []

    def load(self, version: int, config_json: str, tensors: dict[str, np.ndarray]) -> bool:
        """Take a newer policy (ValueError if it does not fit); a phase change starts a new skill."""
        if version <= self.version:
            return False
        cfg = SkildPolicyConfig.from_json(config_json)
        nets = networks(cfg, self.seed)
        import_tensors(nets, tensors)
        if self.cfg is not None and cfg.phase != self.cfg.phase:
            self.left = 0
        self.cfg, self.nets, self.version = cfg, nets, version
        return True

    @property
    def phase(self) -> str:
        return self.cfg.phase if self.cfg is not None else ""

    def reset(self) -> None:
        self.left = 0

    @torch.no_grad()
    def _pick(self, features: torch.Tensor) -> None:
        cfg = self.cfg
        if cfg.phase == "task":
            option = int(self.nets["task"].distribution(features).sample()[0])
            self.slot, self.b = (option // cfg.k if cfg.targets else -1), option % cfg.k
        else:
            filled = len(cfg.targets)
            self.slot = int(self.nets["selector"](features, filled)[0].sample()[0]) if filled else -1
            self.b = int(self.rng.integers(0, cfg.k))
        self.left = cfg.skill_steps

    def target(self) -> tuple[int, np.ndarray]:
        """The running skill's ``(factor, row)`` (no target: factor 0, the empty row)."""
        if self.slot < 0:
            return 0, np.zeros(self.cfg.num_factors + 1, bool)
        factor, key = self.cfg.targets[self.slot]
        return factor, key_rows(np.array(key), self.cfg.num_factors + 1)

    @torch.no_grad()
    def act(self, observation: np.ndarray) -> np.ndarray:
        features = one_hot_states(np.asarray(observation, dtype=np.int64)[None], self.cfg.sizes)
        started = self.left <= 0
        if started:
            self._pick(features)
        self._labels.append((self.slot, self.b, started))
        self.left -= 1
        epsilon = self.cfg.epsilon if self.cfg.phase == "pretrain" else 0.0
        if self.rng.random() < epsilon:
            return np.array([self.rng.integers(0, self.cfg.actions)], np.float32)
        factor, row = self.target()
        q = self.nets["q"](features, torch.tensor([factor]), torch.as_tensor(row[None]), torch.tensor([self.b]))
        return np.array([int(q.argmax(1)[0])], np.float32)

    def take_labels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(slot int32, b int32, started bool)`` of the steps acted since the last call."""
        slot, b, started = (np.array(x) for x in zip(*self._labels)) if self._labels else ([], [], [])
        self._labels = []
        return np.asarray(slot, np.int32), np.asarray(b, np.int32), np.asarray(started, bool)
