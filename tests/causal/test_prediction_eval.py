"""k-step colour accuracy on Chemical: the metric by hand, and CDL's causal mask makes OOD = ID."""
from __future__ import annotations

import numpy as np
import torch

from causal.baselines import MonolithicModel, dense_rollout_step
from causal.cdl import CDLConfig
from causal.cdl_trainer import CDLTrainer
from causal.factored import FactorLayout
from causal.planning import cdl_rollout_step
from causal.prediction_eval import (
    chemical_color_columns,
    chemical_prediction_data,
    evaluate_chemical_prediction,
    k_step_accuracy,
)
from envs.chemical import ChemicalEnv

ENV = {"graph": "chain", "num_objects": 3}


def test_windows_follow_the_environment_and_the_metric_counts_colour_hits() -> None:
    env = ChemicalEnv(**ENV)
    data = chemical_prediction_data(env, num_starts=70, max_steps=5, seed=0)
    assert data.states.shape == (70, 6, 9) and data.actions.shape == (70, 5, 1) and data.max_steps == 5
    acted = data.actions[:, 0, 0].astype(int) // env.num_colors
    np.testing.assert_array_equal(data.states[np.arange(70), 1, 3 * acted], data.actions[:, 0, 0] % env.num_colors)
    unchanged = k_step_accuracy(lambda s, a: s, data, chemical_color_columns(env))
    by_hand = [(data.states[:, k, 0::3] == data.states[:, 0, 0::3]).mean() for k in range(1, 6)]
    np.testing.assert_allclose(unchanged, by_hand, rtol=1e-6)


def test_cdl_with_its_causal_mask_predicts_ood_states_as_well_as_id_states() -> None:
    """OOD changes positions only; colours never read them through the parents mask."""
    torch.set_num_threads(1)
    env = ChemicalEnv(**ENV)
    layout = FactorLayout.from_spec(env.env_spec())
    cfg = CDLConfig(feature_hidden=16, feature_dim=16, predictor_hidden=16, lr=3e-3)
    trainer = CDLTrainer(layout, cfg, seed=0)
    trainer.set_parents(env.global_graph.astype(bool))
    data = chemical_prediction_data(env, num_starts=2000, max_steps=1, seed=1)
    s, a, n = (torch.from_numpy(x) for x in (data.states[:, 0], data.actions[:, 0], data.states[:, 1]))
    rng = np.random.default_rng(0)
    for _ in range(400):
        index = torch.from_numpy(rng.integers(0, len(s), 64))
        trainer.update(s[index], a[index], n[index])
    cdl = cdl_rollout_step(trainer.model, torch.from_numpy(env.global_graph.astype(bool)))
    results = evaluate_chemical_prediction(cdl, ENV, noise_scales=(1.0, 100.0), num_starts=300, seed=2)
    assert set(results) == {"id", "ood_1", "ood_100"}
    assert results["id"].shape == (5,) and np.all((results["id"] >= 0) & (results["id"] <= 1))
    np.testing.assert_array_equal(results["ood_100"], results["id"])
    assert results["id"][0] > 0.8, results["id"]
    dense = MonolithicModel(layout, 32, cfg=cfg)
    dense_results = evaluate_chemical_prediction(dense_rollout_step(dense), ENV, (100.0,), num_starts=300, seed=2)
    assert not np.array_equal(dense_results["ood_100"], dense_results["id"])
