"""SkiLD's pure core: graph pooling, history counting and eligibility, rewards, relabelling."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.skild import (DiversityDiscriminator, GraphHistory, SkiLDConfig, graph_matches, hindsight_relabel,
                          key_rows, novelty_reward, object_graphs, row_keys, skill_reward)

torch.set_num_threads(1)  # two cores shared by several jobs: one thread is faster than contention

# three objects (agent: 2 attributes, table: 1, printer: 2) and the action
OBJECTS = ("agent", "agent", "table", "printer", "printer")
SELF = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], dtype=bool)


def graphs_with(*edges: tuple[int, int], batch: int = 1) -> np.ndarray:
    g = np.repeat(SELF[None], batch, axis=0)
    for j, i in edges:
        g[:, j, i] = True
    return g


def test_object_graphs_pool_attribute_edges_onto_objects():
    local = np.zeros((1, 5, 6), dtype=np.uint8)
    local[0, np.arange(5), np.arange(5)] = 1
    local[0, 4, 2] = 1  # printer attribute <- table
    local[0, 3, 5] = 1  # printer attribute <- action
    local[0, 0, 1] = 1  # within the agent: stays a self-edge
    got = object_graphs(local, OBJECTS)
    assert got.shape == (1, 3, 4)
    np.testing.assert_array_equal(got[0], graphs_with((2, 1), (2, 3))[0])


def test_row_keys_round_trip():
    rows = np.random.default_rng(0).random((7, 3, 4)) < 0.5
    np.testing.assert_array_equal(key_rows(row_keys(rows), 4), rows)


def test_history_counts_and_eligibility_after_twenty_sightings():
    history = GraphHistory(num_factors=3, eligible_after=20, max_targets=256)
    history.update(graphs_with(batch=19))
    assert history.targets == []
    history.update(graphs_with((2, 0), (2, 3), batch=5))
    # the agent's and the table's self-only rows: 24 sightings; the printer's: 19, its pick row 5
    assert [f for f, _ in history.targets] == [0, 1]
    history.update(graphs_with(batch=1))
    assert [f for f, _ in history.targets] == [0, 1, 2]
    assert history.count(2, int(row_keys(SELF[2]))) == 20
    counts = history.counts(graphs_with((2, 0), (2, 3), batch=2))
    np.testing.assert_array_equal(counts, [[25, 25, 5], [25, 25, 5]])
    factors, rows = history.target_arrays(4)
    np.testing.assert_array_equal(factors, [0, 1, 2])
    np.testing.assert_array_equal(rows, SELF)
    assert history.counts(graphs_with((1, 3)))[0, 1] == 0


def test_history_caps_the_number_of_targets():
    history = GraphHistory(num_factors=3, eligible_after=1, max_targets=4)
    rng = np.random.default_rng(1)
    history.update(rng.random((200, 3, 4)) < 0.5)
    assert len(history.targets) == 4 and history.seen() > 4
    restored = GraphHistory(3, 1, 4)
    restored.load_state_dict(history.state_dict())
    assert restored.targets == history.targets and restored.seen() == history.seen()


def test_novelty_reward_is_inverse_square_root_of_counts():
    np.testing.assert_allclose(novelty_reward(np.array([[1, 4, 100], [0, 1, 1]])), [1.6, 3.0])


def test_skill_reward_on_hand_made_graphs():
    pick = graphs_with((2, 0), (2, 3))[0]      # agent, printer, action -> printer
    on_table = graphs_with((2, 1))[0]          # table, printer -> printer
    induced = np.stack([pick, pick, on_table, pick])
    factor = np.array([2, 2, 2, 0])
    row = np.stack([pick[2], on_table[2], on_table[2], SELF[0]])
    log_q = np.log(np.array([0.25, 0.9, 0.5, 0.9]))
    np.testing.assert_array_equal(graph_matches(induced, factor, row), [True, False, True, True])
    got = skill_reward(induced, factor, row, log_q, diversity_weight=0.5)
    np.testing.assert_allclose(got, [1 + 0.5 * np.log(0.25), 0.0, 1 + 0.5 * np.log(0.5), 1 + 0.5 * np.log(0.9)],
                               rtol=1e-6)
    # a discriminator sure of another b never makes inducing the target worse than missing it
    assert skill_reward(induced[:1], factor[:1], row[:1], np.array([-50.0]), 0.5)[0] == pytest.approx(0.0)
    np.testing.assert_array_equal(skill_reward(induced, factor, row, log_q, 0.0), [1, 0, 1, 1])


def test_hindsight_relabelling_keeps_rewards_consistent():
    rng = np.random.default_rng(2)
    b = 4000
    induced = rng.random((b, 3, 4)) < 0.3
    induced[:, np.arange(3), np.arange(3)] = True
    factor = rng.integers(0, 3, b)
    row = rng.random((b, 4)) < 0.5
    counts = rng.integers(1, 50, (b, 3))
    new_factor, new_row, relabelled = hindsight_relabel(induced, factor, row, counts, 7 / 8, rng)
    assert relabelled.mean() == pytest.approx(7 / 8, abs=0.02)
    np.testing.assert_array_equal(new_factor[~relabelled], factor[~relabelled])
    np.testing.assert_array_equal(new_row[~relabelled], row[~relabelled])
    log_q = np.log(rng.uniform(0.2, 1.0, b))
    reward = skill_reward(induced, new_factor, new_row, log_q, 0.5)
    # every relabelled sample induced its new target, so it is paid as if that had been the skill
    assert graph_matches(induced, new_factor, new_row)[relabelled].all()
    np.testing.assert_allclose(reward[relabelled], 1 + 0.5 * np.maximum(log_q[relabelled], -2), rtol=1e-6)
    np.testing.assert_array_equal(reward[~relabelled] > 0, graph_matches(induced, factor, row)[~relabelled])


def test_relabelling_prefers_rarely_seen_rows():
    rng = np.random.default_rng(3)
    b = 20000
    induced = np.repeat(SELF[None], b, axis=0)
    counts = np.tile([1, 100, 10000], (b, 1))
    new_factor, _, _ = hindsight_relabel(induced, np.zeros(b, int), SELF[np.zeros(b, int)], counts, 1.0, rng)
    share = np.bincount(new_factor, minlength=3) / b
    expected = np.array([1, 0.1, 0.01]) / 1.11
    np.testing.assert_allclose(share, expected, atol=0.01)


def test_discriminator_learns_to_tell_diversity_indices_apart():
    torch.manual_seed(0)
    q = DiversityDiscriminator(state_features=4, num_factors=3, k=4, hidden=32)
    opt = torch.optim.Adam(q.parameters(), lr=1e-2)
    b = torch.randint(0, 4, (256,))
    features = torch.nn.functional.one_hot(b, 4).float()  # states that reveal b
    factor, row = torch.zeros(256, dtype=torch.long), torch.zeros(256, 4, dtype=torch.bool)
    for _ in range(100):
        opt.zero_grad()
        q.loss(features, factor, row, b).backward()
        opt.step()
    assert q.log_prob(features, factor, row, b).exp().mean().item() > 0.9


def test_config_refuses_bad_values():
    with pytest.raises(ValueError, match="relabel_fraction"):
        SkiLDConfig(relabel_fraction=1.5)
    with pytest.raises(ValueError, match="diversity_k"):
        SkiLDConfig(diversity_k=0)
    with pytest.raises(ValueError, match="relabel_horizon"):
        SkiLDConfig(relabel_horizon=0)
    with pytest.raises(ValueError, match="relabel_random"):
        SkiLDConfig(relabel_random=-0.1)
