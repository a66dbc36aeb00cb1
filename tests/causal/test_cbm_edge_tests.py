"""CBM's graphs with standard errors (issue 22, item 4): its dynamics CMI (eq. 4.3) and reward CMI
(0.5 log MSE ratio) each come with a standard error whose size matches the spread of the estimate over
independent draws of the held-out data, and the reward graph is decided by the same FDR tests."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.cbm import CBMTrainer
from causal.cbm_config import CBMConfig
from causal.edge_tests import EdgeEstimate, decide, fdr_graph
from causal.factored import FactorLayout
from causal.methods.cbm import DynamicsCMI, RewardCMI

torch.set_num_threads(1)
LAYOUT = FactorLayout(("f0", "f1", "f2"), ("continuous", "continuous", "categorical"), (1, 1, 3), (0.0,) * 3,
                      (1.0,) * 3, "continuous", 1)
CFG = CBMConfig(num_negatives=16, eval_negatives=128, lr=3e-3, batch_size=64, feature_hidden=16, feature_dim=16,
                predictor_hidden=16, embed_dim=8, candidate_hidden=16, cmi_samples=4_096)


def toy_batch(g: torch.Generator, b: int) -> tuple[torch.Tensor, ...]:
    """x' = x + a, y' noise, c' = c; reward 0.5 c (test_cbm's toy dynamics)."""
    x, y = torch.rand(b, 1, generator=g) * 2 - 1, torch.rand(b, 1, generator=g) * 2 - 1
    c = torch.randint(0, 3, (b, 1), generator=g).float()
    a = torch.rand(b, 1, generator=g) - 0.5
    nxt = torch.cat([x + a, torch.rand(b, 1, generator=g) * 2 - 1, c], dim=1)
    return torch.cat([x, y, c], dim=1), a, nxt, c[:, 0] * 0.5 + 0.1 * torch.randn(b, generator=g)


@pytest.fixture(scope="module")
def trained() -> CBMTrainer:
    trainer, g = CBMTrainer(LAYOUT, CFG, seed=0), torch.Generator().manual_seed(0)
    for _ in range(60):
        trainer.update(*toy_batch(g, 64))
    return trainer


def spread_ratio(draws: list[EdgeEstimate]) -> np.ndarray:
    """Per entry: the standard deviation of the estimate over independent draws / its mean standard error."""
    cmi = np.stack([d.cmi for d in draws])
    se = np.stack([d.stderr for d in draws]).mean(axis=0)
    return cmi.std(axis=0, ddof=1)[se > 0] / se[se > 0]


def test_dynamics_standard_errors_match_the_spread_over_draws(trained: CBMTrainer) -> None:
    """The implicit CMI on 30 independent held-out draws (the negatives held fixed, as the standard
    error assumes): its spread over the draws is what the standard errors say, and the estimate's
    mean is the one ``scores`` gives."""
    g = torch.Generator().manual_seed(1)
    draws = [DynamicsCMI(seed=5).estimate(trained.model, *toy_batch(g, 300)[:3]) for _ in range(30)]
    ratio = spread_ratio(draws)
    assert 0.7 < np.median(ratio) < 1.4, np.round(ratio, 2)
    data = toy_batch(g, 300)[:3]
    np.testing.assert_allclose(DynamicsCMI(seed=5).estimate(trained.model, *data).cmi,
                               DynamicsCMI(seed=5).scores(trained.model, *data), atol=1e-5)
    with pytest.raises(ValueError, match="no permuted-input null"):
        DynamicsCMI().estimate(trained.model, *data, permute=torch.Generator())


def test_reward_standard_errors_match_the_spread_over_draws(trained: CBMTrainer) -> None:
    """The delta-method standard error of the reward CMI against its spread over 100 draws; the same
    CMI as ``scores``."""
    g = torch.Generator().manual_seed(2)
    draws = []
    for _ in range(100):
        s, a, n, r = toy_batch(g, 400)
        draws.append(RewardCMI().estimate(trained.model, s, a, n, r))
    ratio = spread_ratio(draws)
    assert 0.8 < np.median(ratio) < 1.25, np.round(ratio, 2)
    s, a, n, r = toy_batch(g, 400)
    np.testing.assert_allclose(RewardCMI().estimate(trained.model, s, a, n, r).cmi,
                               RewardCMI().scores(trained.model, s, a, n, r), atol=1e-6)


def test_a_reward_graph_is_tested_on_every_entry() -> None:
    """A ``[d_S + 1]`` reward graph has no self-edges: every entry is tested and can be undecided."""
    est = EdgeEstimate(np.array([0.4, 0.006, 0.001, 0.003]), np.array([0.01, 0.0005, 0.0005, 0.004]), 1_000)
    assert fdr_graph(est, 0.05, 5e-4).tolist() == [True, True, False, False]
    edges, open_ = decide(est, "fdr", 0.02, 0.05, 5e-4)
    assert edges.tolist() == [True, True, False, False] and open_.tolist() == [False, False, True, True]
    edges, open_ = decide(est, "fixed", 0.02, 0.05, 5e-4)
    assert edges.tolist() == [True, False, False, False] and not open_.any()
