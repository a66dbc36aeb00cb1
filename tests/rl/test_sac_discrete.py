"""Categorical SAC: a contextual bandit it must solve, the input mask hiding factors from the trained
actor and critics, checkpoints and seeds."""
from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from causal.rl.base import ActionSpec
from causal.rl.replay import UniformReplay
from causal.rl.sac import SACConfig
from causal.rl.sac_discrete import DiscreteSACAgent

ACTIONS = ActionSpec("categorical", 4)
SMALL = SACConfig(hidden=(32, 32), lr=3e-3, init_alpha=0.1, gamma=0.0)


def bandit_batch(agent: DiscreteSACAgent, rng: np.random.Generator, rows: int = 64) -> tuple[np.ndarray, ...]:
    """One-step episodes: observation [context one-hot (4), noise (2)], reward 1 when the action is the
    context. The noise columns carry nothing about the reward."""
    context = rng.integers(0, 4, rows)
    obs = np.concatenate([np.eye(4)[context], rng.normal(size=(rows, 2))], axis=1).astype(np.float32)
    actions = agent.act(obs)
    return obs, actions[:, None], (actions == context).astype(np.float32), obs, np.ones(rows)


def trained_bandit_agent(mask: list[bool] | None, updates: int = 250) -> DiscreteSACAgent:
    torch.set_num_threads(1)
    agent = DiscreteSACAgent(6, ACTIONS, SMALL, seed=0, input_mask=mask)
    replay, rng = UniformReplay(20_000, 6, 1, seed=0), np.random.default_rng(0)
    for _ in range(updates):
        replay.add(*bandit_batch(agent, rng))
        agent.update(replay.sample(64))
    return agent


def test_discrete_sac_solves_a_contextual_bandit_through_its_mask() -> None:
    agent = trained_bandit_agent([True] * 4 + [False] * 2)
    obs = np.concatenate([np.eye(4), np.zeros((4, 2))], axis=1)
    assert agent.act(obs, deterministic=True).tolist() == [0, 1, 2, 3]
    assert agent.version == 250 and agent.alpha != pytest.approx(SMALL.init_alpha)  # the temperature is tuned
    blind = trained_bandit_agent([False] * 4 + [True] * 2, updates=30)
    assert len(set(blind.act(obs, deterministic=True).tolist())) == 1  # it cannot tell the contexts apart


def test_masked_out_factors_change_no_action_no_probability_and_no_q_value() -> None:
    """The abstraction really hides them: after training, values far out of range in the masked-out
    columns leave the actor and both critics (and the targets) exactly as they were; a kept column
    does change them (so this test can fail)."""
    agent = trained_bandit_agent([True] * 4 + [False] * 2, updates=60)
    rng = np.random.default_rng(1)
    obs = np.concatenate([np.eye(4)[rng.integers(0, 4, 256)], rng.normal(size=(256, 2))], axis=1).astype(np.float32)
    shifted = obs.copy()
    shifted[:, 4:] = rng.uniform(5, 50, size=(256, 2)) * rng.choice([-1, 1], size=(256, 2))
    x, y = torch.from_numpy(obs), torch.from_numpy(shifted)
    np.testing.assert_array_equal(agent.act(obs, deterministic=True), agent.act(shifted, deterministic=True))
    torch.testing.assert_close(agent.log_policy(x), agent.log_policy(y), rtol=0, atol=0)
    torch.testing.assert_close(agent.q_values(x), agent.q_values(y), rtol=0, atol=0)
    torch.testing.assert_close(agent.q_values(x, target=True), agent.q_values(y, target=True), rtol=0, atol=0)
    kept_changed = obs.copy()
    kept_changed[:, :4] = np.roll(kept_changed[:, :4], 1, axis=1)
    assert not torch.allclose(agent.log_policy(x), agent.log_policy(torch.from_numpy(kept_changed)))
    agent.set_input_mask(None)
    assert not torch.allclose(agent.q_values(x), agent.q_values(y))


def test_state_round_trips_weights_only_and_seeds_repeat() -> None:
    a, b = trained_bandit_agent(None, updates=20), trained_bandit_agent(None, updates=20)
    for p, q in zip(a.actor.parameters(), b.actor.parameters()):
        torch.testing.assert_close(p, q, rtol=0, atol=0)
    buffer = io.BytesIO()
    torch.save(a.state_dict(), buffer)
    buffer.seek(0)
    c = DiscreteSACAgent(6, ACTIONS, SMALL, seed=5)
    c.load_state_dict(torch.load(buffer, weights_only=True))
    obs = np.random.default_rng(2).normal(size=(32, 6)).astype(np.float32)
    np.testing.assert_array_equal(a.act(obs), c.act(obs))  # the sampling generator travels too
    assert c.version == 20 and c.alpha == pytest.approx(a.alpha, rel=1e-6)


def test_continuous_actions_are_refused() -> None:
    with pytest.raises(ValueError):
        DiscreteSACAgent(3, ActionSpec("continuous", 1, (-1.0,), (1.0,)))
