"""Chapter 3's generalisation experiment core: same data for every model, ID vs OOD, Match with CEM."""
from __future__ import annotations

import numpy as np
import torch

from causal.factored import FactorLayout
from causal.generalisation import (MODELS, MatchConfig, TrainingConfig, carry_extra_columns, match_returns,
                                   prediction_table, random_transitions, reward_inputs, train_dynamics)
from causal.cdl import CDLConfig
from causal.planning import CEMConfig
from envs.chemical import ChemicalEnv

ENV = {"graph": "chain", "num_objects": 3}
SMALL = CDLConfig(feature_hidden=16, feature_dim=16, predictor_hidden=16, lr=3e-3)


def test_random_transitions_split_whole_episodes_and_follow_the_env() -> None:
    train, heldout = random_transitions(ENV, 3000, seed=0, heldout_fraction=0.3)
    assert len(train) + len(heldout) >= 3000 and len(train) % 50 == 0 and len(heldout) % 50 == 0
    assert train.state.shape[1] == 9 and train.action.shape[1] == 1 and train.state.dtype == np.float32
    acted = train.action[:, 0].astype(int) // 5  # the object an action sets (num_colors = 5)
    rows = np.arange(len(train))
    np.testing.assert_array_equal(train.next_state[rows, 3 * acted], train.action[:, 0] % 5)
    again, _ = random_transitions(ENV, 3000, seed=0, heldout_fraction=0.3)
    np.testing.assert_array_equal(again.state, train.state)


def test_carry_extra_columns_copies_trailing_columns() -> None:
    step = carry_extra_columns(lambda s, a: s + 1, state_dim=2)
    out = step(torch.zeros(3, 4), torch.zeros(3, 1))
    assert out[:, :2].eq(1).all() and out[:, 2:].eq(0).all()
    assert reward_inputs(None, 2) == [0, 1, 2, 3, 4, 5, 6, 7]


def test_cdl_ignores_ood_positions_dense_models_do_not_and_cem_uses_every_model() -> None:
    torch.set_num_threads(1)
    env = ChemicalEnv(**ENV)
    train, heldout = random_transitions(ENV, 20_000, seed=0)
    trained = train_dynamics(FactorLayout.from_spec(env.env_spec()), train, heldout,
                             TrainingConfig(updates=400, graph_every=100, cdl=SMALL), seed=0)
    params = trained.parameters()
    assert abs(params["Monolithic"] - params["CDL"]) / params["CDL"] < 0.02 and params["Modular"] == params["CDL"]
    positions = [1, 2, 4, 5, 7, 8]
    colours = [0, 3, 6]
    assert not trained.graph[np.ix_(colours, positions)].any(), "a position -> colour edge was learned"
    table = prediction_table(trained.step_fns(), ENV, noise_scales=(10.0,), num_starts=300, max_steps=3)
    assert set(table) == set(MODELS) and all(len(v["id"]) == 3 for v in table.values())
    assert table["CDL"]["ood_10"] == table["CDL"]["id"]  # the causal mask never reads a position
    assert table["CDL"]["id"][0] > 0.7
    for dense in ("Monolithic", "Modular"):
        assert table[dense]["ood_10"][0] < table[dense]["id"][0] - 0.1, table[dense]
    cfg = MatchConfig(reward_episodes=20, reward_updates=300, episodes=2, parallel=2,
                      cem=CEMConfig(population=16, elites=8, iterations=2))
    returns = match_returns(trained, ENV, (10.0,), cfg, models=("CDL", "Monolithic"))
    assert set(returns) == {"CDL", "Monolithic", "Random"}
    assert all(len(r) == 2 and all(0 <= x <= 50 for x in r) for per in returns.values() for r in per.values())
    assert returns["CDL"]["ood_10"] == returns["CDL"]["id"]  # abstraction and causal rollouts ignore positions
