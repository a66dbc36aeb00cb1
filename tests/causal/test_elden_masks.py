"""Table 5.1's Input Mask and Attention Mask baselines (ch. 5.3.1): the mask bounds what each output
reads, an all-open mask is ELDEN's network, samples and scores have the right shapes and ranges, the
sparsity settings close entries, and trained on a gated toy the masks find the dependencies."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from causal.elden import ELDENConfig, ensemble_forward
from causal.elden_masks import MaskConfig, MaskedELDENModel, MaskTrainer, mask_graphs
from causal.factored import FactorLayout
from causal.methods.elden import MASK_ESTIMATORS

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = ELDENConfig(members=2, token_hidden=8, embed_dim=8, heads=2, predictor_hidden=8, member_batch=8)
TOY = ELDENConfig(members=2, token_hidden=16, embed_dim=16, heads=2, predictor_hidden=16, member_batch=32,
                  lr=1e-2, grad_reg=0.0)
GATED = FactorLayout(names=("g", "i", "j"), kinds=("categorical",) * 3, sizes=(2, 2, 2), locs=(0.0,) * 3,
                     scales=(1.0,) * 3, action_kind="categorical", action_size=2)
"""The toy: ``g`` and ``i`` are redrawn every step; ``j`` copies ``i`` when the gate ``g`` is on and keeps
its value when it is off, so ``i -> j`` is an edge exactly when ``g = 1``."""


def gated(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    state, action, nxt = rng.integers(0, 2, (n, 3)), rng.integers(0, 2, (n, 1)), rng.integers(0, 2, (n, 3))
    nxt[:, 2] = np.where(state[:, 0] == 1, state[:, 1], state[:, 2])
    return tuple(torch.tensor(v, dtype=torch.float32) for v in (state, action, nxt))


def trained(mask: MaskConfig, updates: int = 300) -> MaskTrainer:
    trainer = MaskTrainer(GATED, TOY, mask, seed=0)
    state, action, nxt = gated(4096, 0)
    rng = np.random.default_rng(1)
    for _ in range(updates):
        rows = torch.from_numpy(rng.integers(0, 4096, trainer.batch_size))
        trainer.update(state[rows], action[rows], nxt[rows])
    return trainer


@pytest.mark.parametrize("kind", ["input", "attention"])
def test_a_closed_entry_cuts_its_input_from_its_output(kind: str) -> None:
    torch.manual_seed(0)
    model = MaskedELDENModel(GATED, TINY, MaskConfig(kind=kind))
    state, action, _ = gated(6, 0)
    x = model.per_member(model.encode(state, action)).clone().requires_grad_(True)
    mask = torch.ones(2, 6, 3, 4)
    mask[:, :, 2, 1] = 0.0  # i -> j closed
    out = model.masked_raw(model.params(), x, mask)
    (grad,) = torch.autograd.grad(out[:, :, 2].sum(), x, retain_graph=True)
    assert grad[:, :, 1].abs().max() == 0.0
    assert grad[:, :, 0].abs().max() > 1e-4 and grad[:, :, 3].abs().max() > 1e-4
    (grad,) = torch.autograd.grad(out[:, :, 0].sum(), x)
    assert grad[:, :, 1].abs().max() > 1e-4  # row g keeps reading i


@pytest.mark.parametrize("kind", ["input", "attention"])
def test_an_all_open_mask_is_eldens_network(kind: str) -> None:
    torch.manual_seed(0)
    model = MaskedELDENModel(GATED, TINY, MaskConfig(kind=kind))
    state, action, _ = gated(5, 1)
    x = model.per_member(model.encode(state, action))
    full = ensemble_forward(model.params(), x, TINY.heads)[0]
    masked = model.masked_raw(model.params(), x, torch.ones(2, 5, 3, 4))
    torch.testing.assert_close(masked, full, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("kind", ["input", "attention"])
def test_scores_samples_and_estimators_have_their_shapes_and_ranges(kind: str) -> None:
    torch.manual_seed(0)
    model = MaskedELDENModel(GATED, TINY, MaskConfig(kind=kind))
    state, action, nxt = gated(700, 2)
    graphs = mask_graphs(model, state, action, chunk=256)
    assert graphs.shape == (700, 3, 4) and graphs.min() >= 0.0 and graphs.max() <= 1.0
    x = model.per_member(model.encode(state[:50], action[:50]))
    sample, scores = model.sample_mask(model.params(), x, torch.Generator().manual_seed(0))
    assert sample.shape == scores.shape == (2, 50, 3, 4)
    if kind == "input":
        assert set(sample.unique().tolist()) <= {0.0, 1.0}
    else:
        assert sample.min() >= 0.0 and sample.max() <= 1.0 and (sample[scores == 0] == 0).all()
    estimator = MASK_ESTIMATORS[f"{kind}-mask"]
    np.testing.assert_allclose(estimator.scores(model, state, action, nxt), graphs.numpy(), rtol=1e-6)
    assert estimator.threshold(model) == 0.5


def test_the_kernel_truncation_closes_far_entries() -> None:
    x = None
    opened = []
    for truncation in (1.5, 1.0, 0.5):
        torch.manual_seed(0)
        model = MaskedELDENModel(GATED, TINY, MaskConfig(kind="attention", truncation=truncation))
        if x is None:
            state, action, _ = gated(200, 3)
            x = model.per_member(model.encode(state, action))
        opened.append(model.kernel(model.params(), x) > 0)
    assert opened[0].float().mean() > opened[1].float().mean() > opened[2].float().mean() > 0
    assert (opened[0] >= opened[1]).all() and (opened[1] >= opened[2]).all()


def test_the_l1_term_closes_what_the_outputs_do_not_need() -> None:
    state, action, _ = gated(512, 5)
    sparse = mask_graphs(trained(MaskConfig(kind="input", mask_hidden=32, sparsity=0.1)).model, state, action)
    dense = mask_graphs(trained(MaskConfig(kind="input", mask_hidden=32, sparsity=0.0)).model, state, action)
    assert sparse[:, 2, 1].mean() > 0.95 and sparse[:, 2, 2].mean() > 0.95  # j's parents stay open
    assert sparse[:, 0].mean() < 0.05  # g is redrawn: it needs no input
    assert dense[:, 0].mean() > 0.5 and dense.mean() > sparse.mean() + 0.3


def test_the_attention_mask_opens_i_to_j_when_the_gate_is_on() -> None:
    model = trained(MaskConfig(kind="attention", mask_hidden=32)).model
    state, action, _ = gated(512, 5)
    graphs = mask_graphs(model, state, action)
    on = state[:, 0] == 1
    assert graphs[on, 2, 1].mean() > graphs[~on, 2, 1].mean() + 0.2
    assert graphs[:, 2, 3].mean() < 0.05  # the action never matters to j


def test_training_is_seeded_and_resumes_from_a_checkpoint() -> None:
    state, action, nxt = gated(64, 7)
    runs = []
    for _ in range(2):
        trainer = MaskTrainer(GATED, TINY, MaskConfig(kind="input"), seed=3)
        trainer.update(state[:16], action[:16], nxt[:16])
        saved = copy.deepcopy(trainer.state_dict())
        runs.append(trainer.update(state[16:32], action[16:32], nxt[16:32]))
    assert runs[0] == runs[1]
    resumed = MaskTrainer(GATED, TINY, MaskConfig(kind="input"), seed=99)
    resumed.load_state_dict(saved)
    assert resumed.update(state[16:32], action[16:32], nxt[16:32]) == runs[0]


def test_mask_config_is_checked() -> None:
    for bad in ({"kind": "output"}, {"sparsity": -1.0}, {"truncation": 0.0}, {"mask_hidden": 0}):
        with pytest.raises(ValueError):
            MaskConfig(**bad)
