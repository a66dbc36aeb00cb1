"""Intrinsic rewards: hand-computed values, the model's own masked NLL, registry, and the scoring core."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from causal.cdl import CDLConfig, CDLModel, model_config_json
from causal.method import export_tensors
from causal.factored import FactorLayout
from causal.intrinsic import REWARDS, BootstrapEnsemble, Disagreement, PredDiff, PredictionError, make_reward, score
from proto.codec import decode, encode
from proto.messages import GraphReport, Weights
from services.runtime.config import build_config
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.intrinsic_reward.core import IntrinsicRewardCore

TINY = CDLConfig(feature_hidden=8, feature_dim=8, predictor_hidden=8)
LAYOUT = FactorLayout(names=("c", "x"), kinds=("categorical", "continuous"), sizes=(3, 1), locs=(0.0, 0.0),
                      scales=(1.0, 1.0), action_kind="categorical", action_size=2)


def transitions(n: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    state = np.stack([rng.integers(0, 3, n), rng.normal(0, 1, n)], 1).astype(np.float32)
    nxt = np.stack([rng.integers(0, 3, n), rng.normal(0, 1, n)], 1).astype(np.float32)
    action = rng.integers(0, 2, (n, 1)).astype(np.float32)
    return torch.from_numpy(state), torch.from_numpy(action), torch.from_numpy(nxt)


def constant_model(logits: list[float], mean: float, log_std: float) -> CDLModel:
    """Every parameter 0 except the last head bias: predictions ignore the inputs entirely."""
    model = CDLModel(LAYOUT, TINY)
    with torch.no_grad():
        for p in model.parameters():
            p.zero_()
        model.head_b3[0, 0, :3] = torch.tensor(logits)
        model.head_b3[1, 0, :2] = torch.tensor([mean, log_std])
    return model


def test_hand_computed_values_on_an_input_free_model() -> None:
    logits, mean, log_std = [0.5, -1.0, 2.0], 0.3, -0.5
    model = constant_model(logits, mean, log_std)
    s, a, n = transitions()
    log_softmax = np.array(logits) - math.log(sum(math.exp(v) for v in logits))
    z = (n[:, 1].numpy() - s[:, 1].numpy() - mean) / math.exp(log_std)
    expected_nll = -log_softmax[n[:, 0].long().numpy()] + 0.5 * z**2 + log_std + 0.5 * math.log(2 * math.pi)
    parents = np.array([[1, 0, 0], [0, 1, 1]], np.uint8)
    np.testing.assert_allclose(PredictionError(eta=2.0)(model, parents, s, a, n).numpy(), 2 * expected_nll, rtol=1e-5)
    np.testing.assert_allclose(PredDiff(eta=3.0)(model, parents, s, a, n).numpy(), 0.0, atol=1e-6)


@pytest.mark.parametrize("eta", [0.5, 2.0])
def test_batched_rewards_match_the_models_own_masked_nll(eta: float) -> None:
    torch.manual_seed(3)
    model = CDLModel(LAYOUT, TINY)
    s, a, n = transitions(32, seed=1)
    parents = np.array([[0, 1, 1], [0, 0, 0]], np.uint8)  # no self-edges given: they are forced
    causal_mask = torch.tensor([[True, True, True], [False, True, False]])
    dense = model.masked_nll(s, a, n, torch.ones(2, 3, dtype=torch.bool))
    causal = model.masked_nll(s, a, n, causal_mask)
    with torch.no_grad():
        expected_preddiff = torch.tanh(eta * (causal - dense).sum(0))
        expected_curiosity = eta * causal.sum(0)
    got = PredDiff(eta=eta)(model, parents, s, a, n)
    assert not torch.allclose(got, torch.zeros_like(got))
    torch.testing.assert_close(got, expected_preddiff, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(PredictionError(eta=eta)(model, parents, s, a, n), expected_curiosity, rtol=1e-5, atol=1e-5)
    chunked = score(make_reward("preddiff", eta), model, parents, s.numpy(), a.numpy(), n.numpy(), chunk=5)
    np.testing.assert_allclose(chunked, expected_preddiff.numpy(), rtol=1e-5, atol=1e-6)


def test_registry() -> None:
    assert set(REWARDS) == {"preddiff", "curiosity", "disagreement", "elden"}
    assert make_reward("curiosity", 2.0) == PredictionError(eta=2.0)
    assert make_reward("elden", 0.5).eta == 0.5 and make_reward("elden").source == "dynamics"
    assert make_reward("preddiff").warmup_env_steps(None) == 0
    with pytest.raises(KeyError, match="known"):
        make_reward("nope")


def test_core_scores_batches_with_the_newest_weights_and_graph() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=64))
    spec, batch = worker.spec, worker.collect()
    core = IntrinsicRewardCore(IntrinsicRewardConfig(eta=1.0), spec)
    before = core.score(batch)
    assert before.weights_version == 0 and (before.intrinsic_reward == 0).all()
    layout = FactorLayout.from_spec(spec)
    torch.manual_seed(0)
    model = CDLModel(layout, TINY)
    weights = Weights(model="cdl", version=3, config_json=model_config_json(layout, TINY), tensors=export_tensors(model))
    assert core.load_weights(weights) and not core.load_weights(weights)
    graph = np.eye(9, 10, dtype=np.uint8)
    graph[:, 9] = 1
    report = GraphReport(kind="cdl", weights_version=3, env_steps=0, updates=0, factor_names=spec.factor_names,
                         cmi=np.zeros((9, 10), np.float32), adjacency=graph, threshold=0.02, controllable=(),
                         action_relevant=(), action_irrelevant=tuple(range(9)))
    assert core.apply_graph(report)
    scored = decode(encode(core.score(batch)))
    assert scored.weights_version == 3 and scored.reward_kind == "preddiff"
    expected = score(PredDiff(), model, graph, batch.state, batch.action, batch.next_state)
    np.testing.assert_allclose(scored.intrinsic_reward, expected, rtol=1e-5, atol=1e-6)
    assert np.abs(scored.intrinsic_reward).max() > 0


def test_disagreement_is_the_variance_across_members_by_hand() -> None:
    ensemble = BootstrapEnsemble(LAYOUT, members=3, hidden=4)
    outputs = torch.tensor([[0.0, 1.0, 2.0, 0.5, 0.0, 0.0], [1.0, 1.0, 0.0, 0.5, 0.0, 0.0],
                            [2.0, 1.0, 1.0, 2.0, 0.0, 0.0]])
    with torch.no_grad():
        for p in ensemble.parameters():
            p.zero_()
        ensemble.biases[-1][:, 0, :] = outputs
    s, a, n = transitions(4)
    expected = float(np.var(outputs.numpy(), axis=0).sum())  # 2/3 + 0 + 2/3 + 0.5
    torch.testing.assert_close(Disagreement(eta=2.0)(ensemble, None, s, a, n), torch.full((4,), 2 * expected))


def test_bootstrap_members_agree_where_they_were_trained_and_not_elsewhere() -> None:
    ensemble = BootstrapEnsemble(LAYOUT, members=5, hidden=32, lr=3e-3, seed=1)
    s, _, n = transitions(512, seed=2)
    seen_action, unseen_action = torch.zeros(512, 1), torch.ones(512, 1)
    ensemble.add(s.numpy(), seen_action.numpy(), n.numpy())
    assert ensemble.rows["boot"][:512].std() > 0.5  # Poisson(1) weights, different per member
    before = ensemble.disagreement(s, seen_action).mean()
    losses = [ensemble.train_step(128) for _ in range(300)]
    assert losses[-1] < losses[0]
    seen, unseen = ensemble.disagreement(s, seen_action).mean(), ensemble.disagreement(s, unseen_action).mean()
    assert seen < before and seen < 0.5 * unseen


def test_core_trains_its_ensemble_after_scoring() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, num_objects=3, batch_steps=256))
    core = IntrinsicRewardCore(IntrinsicRewardConfig(reward="disagreement", ensemble_warmup=256,
                                                     ensemble_updates_per_batch=4), worker.spec)
    first = core.score(worker.collect())
    assert first.weights_version == 0 and (first.intrinsic_reward == 0).all()
    second = core.score(worker.collect())
    assert second.weights_version == 4 and second.reward_kind == "disagreement"
    assert (second.intrinsic_reward > 0).all() and core.ensemble.updates == 8
