"""SkiLD's learners and registry entry: a short pre-training run, its replayed rewards, the method."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from causal.methods import get_method, model_from_config_json
from causal.skild import SkiLDConfig, graph_matches
from causal.skild_agent import SkillLearnerConfig, one_hot_states
from causal.skild_pretrain import PretrainConfig, coverage, describe_row, multi_object, pretrain

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
