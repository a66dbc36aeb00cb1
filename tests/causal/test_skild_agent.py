"""SkiLD's learners and registry entry: a short pre-training run, its replayed rewards, the method."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from causal.methods import get_method, model_from_config_json
from causal.skild import SkiLDConfig, graph_matches
from causal.skild_agent import SkillLearnerConfig, SkillReplay, one_hot_states
from causal.skild_pretrain import PretrainConfig, coverage, describe_row, multi_object, pretrain, target_hit_rates

torch.set_num_threads(1)

TINY = SkillLearnerConfig(hidden=32, batch_size=32, learning_starts=64, selector_batch=8, eps_decay_steps=200)


def test_one_hot_states_concatenates_factor_one_hots():
    got = one_hot_states(np.array([[0, 2], [1, 0]]), (2, 3))
    np.testing.assert_array_equal(got.numpy(), [[1, 0, 0, 0, 1], [0, 1, 1, 0, 0]])


@pytest.fixture(scope="module")
def trained():
    run = PretrainConfig(env="installing-printer", env_steps=400, num_envs=4)
    return pretrain(run, SkiLDConfig(eligible_after=5), TINY, mode="skild", seed=0)


def test_pretraining_fills_the_history_and_learns(trained):
    agent, envs = trained
    assert len(agent.history.targets) >= 3 and agent.updates > 0
    assert agent.replay.size == 400
    factors, rows = agent.history.target_arrays(4)
    assert rows[np.arange(len(factors)), factors].all()  # every target keeps its self-edge
    assert describe_row(2, 0b1101, ("agent", "table", "printer")) == "agent, printer, action -> printer"
    assert multi_object(2, 0b1101, 4) and not multi_object(2, 0b1100, 4)


def test_replayed_rewards_pay_exactly_the_induced_targets(trained):
    agent, _ = trained
    batch = agent.replay.sample(256, np.random.default_rng(0))
    reward, labels, log_q = agent.rewards(batch, agent.features(batch["next_state"]))
    match = graph_matches(batch["induced"], labels["factor"], labels["row"])
    np.testing.assert_array_equal(reward[~match], 0.0)
    np.testing.assert_allclose(reward[match], 1 + 0.5 * np.maximum(log_q[match], -2.0), rtol=1e-5)
    assert match.mean() > 0.8  # 7/8 relabelled to what they induced, plus the skills that succeeded


def _replay_rows(count: int, n: int = 2) -> dict[str, np.ndarray]:
    return {"state": np.zeros((count, 3), int), "action": np.zeros(count, int), "next_state": np.zeros((count, 3), int),
            "terminated": np.zeros(count, bool), "induced": np.zeros((count, n, n + 1), bool),
            "factor": np.zeros(count, int), "row": np.zeros((count, n + 1), bool), "b": np.zeros(count, int),
            "counts": np.ones((count, n), int)}


def test_the_replay_links_each_step_to_the_next_of_its_episode_only():
    replay = SkillReplay(capacity=64, state_dim=3, num_factors=2)
    # two envs stepped together (one row each per add), env 1's episode ends after its step 2
    for t in range(5):
        replay.add(stream=np.array([0, 1]), episode=np.array([1, 2 if t < 3 else 3]),
                   step=np.array([t, t if t < 3 else t - 3]), **_replay_rows(2))
    # a worker's batch: one stream, consecutive steps in one add
    replay.add(stream=np.full(4, 7), episode=np.full(4, 5), step=np.arange(4), **_replay_rows(4))
    successor = replay.fields["successor"][: replay.size]
    np.testing.assert_array_equal(successor[0:10:2], [2, 4, 6, 8, -1])  # env 0: one episode
    np.testing.assert_array_equal(successor[1:10:2], [3, 5, -1, 9, -1])  # env 1: a new episode at t = 3
    np.testing.assert_array_equal(successor[10:14], [11, 12, 13, -1])
    rng = np.random.default_rng(0)
    start = np.repeat(np.arange(14), 200)
    later = replay.future(start, horizon=4, rng=rng)
    f = replay.fields
    same = (f["stream"][later] == f["stream"][start]) & (f["episode"][later] == f["episode"][start])
    assert same.all()
    hops = f["step"][later] - f["step"][start]
    assert hops.min() == 0 and hops.max() == 3
    # env 0's step 0 has 4 later steps in reach: the hop is uniform over 0..3
    np.testing.assert_allclose(np.bincount(hops[start == 0], minlength=4) / 200, 0.25, atol=0.08)
    # env 1's step 2 ends its episode: it can only stay
    assert (later[start == 5] == 5).all()
    # rows added without episodes are never linked
    replay.add(**_replay_rows(2))
    assert (replay.future(np.array([14, 15]), 4, rng) == [14, 15]).all()


def test_rows_the_ring_overwrites_drop_their_links():
    replay = SkillReplay(capacity=4, state_dim=3, num_factors=2)
    replay.add(stream=np.zeros(3, int), episode=np.zeros(3, int), step=np.arange(3), **_replay_rows(3))
    assert replay.fields["successor"][0] == 1 and replay.fields["successor"][1] == 2
    replay.add(stream=np.full(2, 1), episode=np.full(2, 9), step=np.arange(2), **_replay_rows(2))  # overwrites 3, 0
    np.testing.assert_array_equal(replay.fields["successor"], [-1, 2, -1, 0])
    replay.add(stream=np.full(2, 1), episode=np.full(2, 9), step=np.arange(2, 4), **_replay_rows(2))  # 1, 2
    # row 0 (stream 1, step 1) links to row 1 (step 2); the old row 1 -> 2 link now joins stream 1's steps 2, 3
    later = replay.future(np.full(100, 3), horizon=3, rng=np.random.default_rng(1))
    assert set(replay.fields["step"][later].tolist()) <= {0, 1, 2}
    assert (replay.fields["stream"][later] == 1).all()


def test_restored_links_continue_each_stream_from_its_newest_row_in_a_wrapped_ring():
    replay = SkillReplay(capacity=4, state_dim=3, num_factors=2)
    for t in range(3):  # two streams, 6 rows in a ring of 4: stream 0's newest is row 0, stream 1's row 1
        replay.add(stream=np.array([0, 1]), episode=np.array([5, 6]), step=np.array([t, t]), **_replay_rows(2))
    copy = SkillReplay(capacity=4, state_dim=3, num_factors=2)
    copy.fields = {k: v.copy() for k, v in replay.fields.items()}
    copy.size, copy.next = replay.size, replay.next
    copy.restore_links()
    assert copy._last == {0: 0, 1: 1}
    copy.add(stream=np.array([1, 0]), episode=np.array([6, 5]), step=np.array([3, 3]), **_replay_rows(2))  # rows 2, 3
    assert copy.fields["successor"][1] == 2 and copy.fields["successor"][0] == 3


def test_future_hindsight_targets_come_from_later_steps_and_pay_only_where_induced():
    """A rare row induced only at each episode's last step: with the future strategy, earlier steps are
    relabelled to it too, unpaid (they did not induce it); paid exactly where their own graph matches."""
    cfg, n = SkiLDConfig(relabel_horizon=5, relabel_fraction=1.0), 2
    from causal.skild_agent import SkiLDAgent
    agent = SkiLDAgent((3, 3, 3), n, 4, cfg, SkillLearnerConfig(batch_size=64), seed=0)
    rows = _replay_rows(40, n)
    rows["induced"][:, np.arange(n), np.arange(n)] = True
    last = np.arange(40) % 5 == 4
    rows["induced"][last, 1, 0] = True  # object 1 depends on object 0, only at the episode's last step
    rows["counts"][:] = 1000
    rows["counts"][last, 1] = 1  # rare: relabelling prefers it
    agent.replay.add(stream=np.zeros(40, int), episode=np.arange(40) // 5, step=np.arange(40) % 5, **rows)
    rng = np.random.default_rng(0)
    index = agent.replay.sample_index(4000, rng)
    achieved = agent.replay.rows(agent.replay.future(index, cfg.relabel_horizon, rng))
    batch = agent.replay.rows(index)
    reward, labels, log_q = agent.rewards(batch, agent.features(batch["next_state"]), achieved)
    rare = labels["row"][:, 0] & (labels["factor"] == 1)
    assert rare[~last[index]].mean() > 0.3  # earlier steps take the later, rare row as their target
    match = graph_matches(batch["induced"], labels["factor"], labels["row"])
    assert not match[rare & ~last[index]].any()
    np.testing.assert_array_equal(reward[~match], 0.0)
    np.testing.assert_allclose(reward[match], 1 + 0.5 * np.maximum(log_q[match], -2.0), rtol=1e-5)


def test_n_step_returns_sum_the_episode_s_next_rewards_for_the_sample_s_skill():
    from causal.skild_agent import SkiLDAgent
    n, gamma = 2, 0.5
    agent = SkiLDAgent((3, 3, 3), n, 4, SkiLDConfig(relabel_fraction=0.0, diversity_weight=0.0),
                       SkillLearnerConfig(gamma=gamma, n_step=3), seed=0)
    rows = _replay_rows(8, n)
    rows["induced"][:, np.arange(n), np.arange(n)] = True
    target = np.array([True, True, False])  # object 1 depends on object 0
    rows["factor"][:], rows["row"][:] = 1, target
    rows["induced"][[1, 2, 4], 1, 0] = True  # induced at steps 1, 2 and 4
    rows["terminated"][4] = True  # episode 0 ends at its step 4; episode 1 has rows 5-7
    agent.replay.add(stream=np.zeros(8, int), episode=np.array([0] * 5 + [1] * 3), step=np.array([0, 1, 2, 3, 4, 0, 1, 2]),
                     **rows)
    index = np.arange(8)
    batch = agent.replay.rows(index)
    reward, labels, _ = agent.rewards(batch, agent.features(batch["next_state"]))
    np.testing.assert_array_equal(reward, [0, 1, 1, 0, 1, 0, 0, 0])
    ret, last, discount = agent._n_step(index, batch, reward, labels)
    np.testing.assert_allclose(ret, [0 + 0.5 + 0.25, 1 + 0.5, 1 + 0.25, 0.5, 1, 0, 0, 0])
    np.testing.assert_array_equal(last, [2, 3, 4, 4, 4, 7, 7, 7])
    # bootstrap after 3 steps; none past the terminal step; the newest rows bootstrap where the replay ends
    np.testing.assert_allclose(discount, [0.125, 0.125, 0, 0, 0, 0.125, 0.25, 0.5])


def test_ending_on_the_target_stops_the_return_where_the_skill_first_induces_it():
    from causal.skild_agent import SkiLDAgent
    n = 2
    agent = SkiLDAgent((3, 3, 3), n, 4, SkiLDConfig(relabel_fraction=0.0, diversity_weight=0.0),
                       SkillLearnerConfig(gamma=0.5, n_step=3, end_on_target=True), seed=0)
    rows = _replay_rows(5, n)
    rows["induced"][:, np.arange(n), np.arange(n)] = True
    rows["factor"][:], rows["row"][:] = 1, np.array([True, True, False])
    rows["induced"][[1, 2], 1, 0] = True
    agent.replay.add(stream=np.zeros(5, int), episode=np.zeros(5, int), step=np.arange(5), **rows)
    index = np.arange(5)
    batch = agent.replay.rows(index)
    reward, labels, _ = agent.rewards(batch, agent.features(batch["next_state"]))
    ret, last, discount = agent._n_step(index, batch, reward, labels)
    np.testing.assert_allclose(ret, [0.5, 1, 1, 0, 0])
    np.testing.assert_array_equal(last, [1, 1, 2, 4, 4])
    np.testing.assert_allclose(discount, [0, 0, 0, 0.25, 0.5])  # rows 3-4 bootstrap where the replay ends


def test_random_targets_come_uniformly_from_the_history_and_are_paid_only_where_induced():
    from causal.skild_agent import SkiLDAgent
    n = 2
    agent = SkiLDAgent((3, 3, 3), n, 4, SkiLDConfig(relabel_fraction=0.0, relabel_random=0.5),
                       SkillLearnerConfig(), seed=0)
    agent.history.targets.extend([(0, 0b100), (1, 0b010), (1, 0b110)])  # keys: self-only rows and 0 -> 1
    rows = _replay_rows(4000, n)
    rows["induced"][:, np.arange(n), np.arange(n)] = True
    rows["induced"][::2, 1, 0] = True
    rows["factor"][:], rows["row"][:] = 0, np.array([True, False, True])  # a label no target has
    agent.replay.add(**rows)
    batch = agent.replay.rows(np.arange(4000))
    reward, labels, log_q = agent.rewards(batch, agent.features(batch["next_state"]))
    factors, target_rows = agent.history.target_arrays(n + 1)
    drawn = ~((labels["factor"] == 0) & (labels["row"] == [True, False, True]).all(1))
    assert drawn.mean() == pytest.approx(0.5, abs=0.03)
    which = [np.flatnonzero((factors == f) & (target_rows == r).all(1)) for f, r in
             zip(labels["factor"][drawn], labels["row"][drawn])]
    assert all(len(w) == 1 for w in which)
    np.testing.assert_allclose(np.bincount(np.concatenate(which), minlength=3) / drawn.sum(), 1 / 3, atol=0.04)
    match = graph_matches(batch["induced"], labels["factor"], labels["row"])
    np.testing.assert_array_equal(reward > 0, match)


def test_the_learner_refuses_an_n_step_below_one():
    with pytest.raises(ValueError, match="n_step"):
        SkillLearnerConfig(n_step=0)


def test_target_hit_rates_compare_each_skill_with_random_actions_from_the_same_states(trained):
    agent, _ = trained
    rates = target_hit_rates(agent, "installing-printer", segments=8, seed=1, skill_steps=5, num_envs=4)
    assert [r["target"] for r in rates] == [describe_row(int(f), int(k), ("agent", "table", "printer"))
                                             for f, k in zip(*_target_keys(agent))]
    assert all(r["segments"] == 8 and 0 <= r["skill"] <= 1 and 0 <= r["random"] <= 1 for r in rates)
    # the table never moves: its self-only row is induced on every step, whatever the policy
    table = [r for r in rates if r["target"] == "table -> table"]
    assert table and table[0]["skill"] == table[0]["random"] == 1.0


def _target_keys(agent):
    from causal.skild import row_keys
    factors, rows = agent.history.target_arrays(4)
    return factors, row_keys(rows[:, None])[:, 0]


def test_random_skill_coverage_counts_episodes(trained):
    agent, _ = trained
    shares = coverage(agent, "installing-printer", episodes=6, episode_length=30, seed=1, num_envs=3)
    assert shares and all(0 < s <= 1 for s in shares.values())
    assert max(shares.values()) == 1.0  # the table never moves: its self-only row is in every episode


def test_the_diayn_baseline_uses_no_graph():
    run = PretrainConfig(env="installing-printer", env_steps=200, num_envs=4)
    agent, _ = pretrain(run, SkiLDConfig(), TINY, mode="diayn", seed=0)
    assert agent.history.targets == [] and agent.k == TINY.diayn_k and agent.updates > 0


def test_the_method_trains_its_induced_graph_model_under_its_own_name():
    from envs.registry import make_env
    from causal.factored import FactorLayout

    env = make_env("installing-printer")
    layout = FactorLayout.from_spec(env.env_spec())
    method = get_method("skild")
    trainer = method.trainer(layout, SkiLDConfig(), 0)
    obs, _ = env.reset(seed=0)
    states, actions, nxt = [], [], []
    for t in range(64):
        a = t % 5
        new, *_ = env.step(a)
        states.append(obs), actions.append([a]), nxt.append(new)
        obs = new
    s, a, s2 = (torch.as_tensor(np.array(x), dtype=torch.float32) for x in (states, actions, nxt))
    assert "nll_total" in trainer.update(s, a, s2) or trainer.updates == 1
    assert json.loads(trainer.config_json())["model"] == "skild"
    model = model_from_config_json(trainer.config_json())
    model.load_state_dict(trainer.state_dict()["model"])
    scores = method.local_graph.scores(model, s[:8], a[:8], s2[:8])
    assert scores.shape == (8, 12, 13) and method.local_graph.threshold(model) == pytest.approx(0.02)
    assert method.global_graph is None


def test_learned_induced_graphs_keep_self_edges_and_give_unchanged_factors_nothing_else():
    run = PretrainConfig(env="installing-printer", env_steps=160, num_envs=4, graphs="pcmi", dynamics_warmup=64)
    agent, envs = pretrain(run, SkiLDConfig(eligible_after=5), TINY, mode="skild", seed=0)
    assert agent.replay.size == 160 and agent.history.seen() > 0
    from causal.skild_pretrain import LearnedGraphs

    learned = LearnedGraphs(envs, run, seed=0)
    batch = agent.replay.sample(16, np.random.default_rng(0))
    graphs = learned.step(agent, batch["state"], batch["action"], batch["next_state"])
    d = graphs.shape[1]
    assert graphs.shape == (16, d, d + 1) and graphs[:, np.arange(d), np.arange(d)].all()
    unchanged = batch["state"] == batch["next_state"]
    assert unchanged.any() and (graphs[unchanged].sum(axis=1) == 1).all()
    with pytest.raises(ValueError, match="graphs must be one of"):
        PretrainConfig(graphs="oracle")


def test_task_policies_over_skills_and_primitives_report_success_curves(trained):
    from causal.skild_task import SkillOptions, TaskConfig, train_task

    agent, _ = trained
    options = SkillOptions(agent)
    assert options.count == len(agent.history.targets) * agent.k
    factor, row, b = options.skills(np.array([0, options.count - 1]))
    np.testing.assert_array_equal(b, [0, agent.k - 1])
    tiny = TaskConfig(env_steps=300, num_envs=2, decisions=4)
    for policy, cfg in ((agent, tiny), (agent, TaskConfig(**{**tiny.__dict__, "end_on_target": True})), (None, tiny)):
        curve = train_task(policy, "installing-printer", "", cfg, seed=0, episode_length=20)
        assert curve[-1][0] >= 300 and all(np.isnan(s) or 0 <= s <= 1 for _, s in curve)


def test_a_skill_that_ends_on_its_target_stops_on_the_step_it_induces_it(trained):
    from causal.skild_pretrain import HouseholdBatch
    from causal.skild_task import SkillOptions, _execute

    agent, _ = trained
    options = SkillOptions(agent)
    self_only = [o for o in range(options.count) if options.skills(np.array([o]))[1][0].sum() == 1
                 and options.skills(np.array([o]))[0][0] == 1]  # the table: only its self-edge, every step
    envs = HouseholdBatch("installing-printer", 3, 0, seed=0)
    _, ended, used, _ = _execute(agent, options, envs, np.full(3, self_only[0]), end_on_target=True)
    assert used == 3 and not ended.any()
    _, _, used, _ = _execute(agent, options, envs, np.full(3, self_only[0]), end_on_target=False)
    assert used == 3 * agent.cfg.skill_steps


def test_a_seeded_pretraining_run_repeats_exactly():
    run = PretrainConfig(env="installing-printer", env_steps=160, num_envs=4)
    first, _ = pretrain(run, SkiLDConfig(eligible_after=5), TINY, seed=3)
    second, _ = pretrain(run, SkiLDConfig(eligible_after=5), TINY, seed=3)
    assert first.history.state_dict() == second.history.state_dict()
    for a, b in zip(first.q.parameters(), second.q.parameters()):
        assert torch.equal(a, b)


def test_coverage_counts_the_random_skills_that_induced_their_target(trained):
    agent, _ = trained
    hits: dict[str, int] = {}
    coverage(agent, "installing-printer", episodes=4, episode_length=30, seed=2, num_envs=2, hits=hits)
    assert hits["segments"] >= 4 and 0 <= hits["induced"] <= hits["segments"]
