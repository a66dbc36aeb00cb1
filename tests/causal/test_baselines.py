"""Dense baselines: parameter counts matched to CDL, CDL's output format, and they learn."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.baselines import (
    DenseDynamicsTrainer,
    ModularModel,
    MonolithicModel,
    dense_rollout_step,
    match_parameter_count,
    matched_monolithic,
    parameter_count,
)
from causal.cdl import CDLConfig, CDLModel
from causal.factored import FactorLayout
from envs.chemical import ChemicalEnv

SMALL = CDLConfig(feature_hidden=16, feature_dim=16, predictor_hidden=16, lr=3e-3)


@pytest.mark.parametrize(("num_objects", "cfg"), [(5, CDLConfig()), (3, SMALL)])
def test_dense_baselines_have_cdl_parameter_counts(num_objects: int, cfg: CDLConfig) -> None:
    layout = FactorLayout.from_spec(ChemicalEnv(graph="full", num_objects=num_objects).env_spec())
    cdl = CDLModel(layout, cfg)
    target = parameter_count(cdl)
    assert parameter_count(ModularModel(layout, cfg)) == target
    monolithic = matched_monolithic(cdl)
    assert abs(parameter_count(monolithic) - target) <= 0.1 * target
    assert parameter_count(monolithic) == pytest.approx(target, rel=0.01)


def test_match_parameter_count_picks_the_closest_width() -> None:
    build = lambda w: torch.nn.Linear(10, w)  # noqa: E731  (11 parameters per unit of width)
    assert match_parameter_count(111, build) == 10
    assert match_parameter_count(116, build) == 11
    assert match_parameter_count(1, build) == 1


def test_dense_models_learn_chemical_colours_in_cdl_format() -> None:
    torch.set_num_threads(1)
    env = ChemicalEnv(graph="chain", num_objects=3, episode_length=1000)
    layout = FactorLayout.from_spec(env.env_spec())
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    states, actions = [], rng.integers(0, env.action_space.n, 1200)
    for a in actions:
        states.append(obs)
        obs, *_ = env.step(int(a))
    states.append(obs)
    s = torch.from_numpy(np.array(states[:-1]))
    a = torch.from_numpy(actions[:, None].astype(np.float32))
    n = torch.from_numpy(np.array(states[1:]))
    for model in (MonolithicModel(layout, 64, cfg=SMALL), ModularModel(layout, SMALL)):
        trainer = DenseDynamicsTrainer(model, seed=0)
        first = trainer.update(s[:64], a[:64], n[:64])["nll_full"]
        for k in range(300):
            index = torch.from_numpy(rng.integers(0, len(s), 64))
            trainer.update(s[index], a[index], n[index])
        assert model.nll(s, a, n).shape == (9, len(s))
        assert model.nll(s, a, n).mean().item() < first - 0.5
        predicted = dense_rollout_step(model)(s, a)
        colour_accuracy = (predicted[:, 0::3] == n[:, 0::3]).float().mean().item()
        assert colour_accuracy > 0.7, type(model).__name__
