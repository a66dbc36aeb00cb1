"""Policy weights on the wire: what a policy-learner exports and an env-worker rebuilds an actor from.

``Weights(model="policy")`` carries the acting part of an agent (PPO: the actor-critic; SAC: the
actor), its input mask included, and a config naming the algorithm, observation width, action space
and hidden widths. A policy over skills (``options``: the names of :data:`envs.skills.OPTION_NAMES`)
is a categorical policy whose action picks the next skill; the env-worker runs the skills. Pure (no bus): the env-worker imports it to act with the newest policy.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import torch

from causal.rl import ActionSpec, PPOAgent, PPOConfig, SACAgent, SACConfig

MODEL = "policy"
Agent = PPOAgent | SACAgent


def policy_config_json(algo: str, obs_dim: int, action: ActionSpec, hidden: tuple[int, ...],
                       options: tuple[str, ...] = ()) -> str:
    config = {"model": MODEL, "algo": algo, "obs_dim": obs_dim, "action": dataclasses.asdict(action),
              "hidden": list(hidden)}
    if options:
        config["options"] = list(options)
    return json.dumps(config, sort_keys=True)


def policy_options(text: str) -> tuple[str, ...]:
    """The skill options a published policy chooses among (() for a policy over raw actions)."""
    return tuple(json.loads(text).get("options", ()))


def acting_module(agent: Agent) -> torch.nn.Module:
    """The part of ``agent`` a worker needs to act."""
    return agent.net if isinstance(agent, PPOAgent) else agent.actor


def export_policy(agent: Agent) -> dict[str, np.ndarray]:
    return {name: t.detach().cpu().numpy().copy() for name, t in acting_module(agent).state_dict().items()}


def agent_from_config_json(text: str, seed: int, obs_dim: int | None = None) -> Agent:
    """A fresh agent of the published architecture (ValueError for a config that is not a policy,
    or not for observations of width ``obs_dim`` when given)."""
    data = json.loads(text)
    if data.get("model") != MODEL:
        raise ValueError(f"not a policy config: {data.get('model')!r}")
    if obs_dim is not None and int(data["obs_dim"]) != obs_dim:
        raise ValueError(f"policy for observations of width {data['obs_dim']}, this env has {obs_dim}")
    action = ActionSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in data["action"].items()})
    hidden = tuple(int(h) for h in data["hidden"])
    if data["algo"] == "ppo":
        return PPOAgent(int(data["obs_dim"]), action, PPOConfig(hidden=hidden), seed=seed)
    if data["algo"] == "sac":
        return SACAgent(int(data["obs_dim"]), action, SACConfig(hidden=hidden), seed=seed)
    raise ValueError(f"unknown policy algorithm {data['algo']!r}")


def warm_up() -> None:
    """Pay the one-off costs of building an agent (torch's lazy optimiser imports take seconds), so
    a worker that goes live afterwards loads its first policy in milliseconds."""
    PPOAgent(1, ActionSpec("categorical", 2), PPOConfig(hidden=(1,)))


def import_policy(agent: Agent, tensors: dict[str, np.ndarray]) -> None:
    """Load published tensors into ``agent``'s acting module (ValueError on any mismatch)."""
    try:
        acting_module(agent).load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in tensors.items()})
    except RuntimeError as exc:
        raise ValueError(f"policy tensors do not fit: {exc}") from None
