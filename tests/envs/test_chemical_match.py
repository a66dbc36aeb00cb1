"""Chemical Match: gymnasium contract, goal construction, reward semantics and the extended spec."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from envs.chemical_match import ChemicalMatchEnv, with_goal_factors
from proto.codec import decode, encode
from proto.messages import EnvSpec


@pytest.mark.parametrize("config", [{}, {"graph": "chain", "num_objects": 3, "ood_noise_scale": 10.0}])
def test_check_env_passes_without_warnings(config: dict) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(ChemicalMatchEnv(**config), skip_render_check=True)


def test_goal_is_appended_constant_and_reproducible() -> None:
    env = ChemicalMatchEnv(graph="full", num_objects=5, episode_length=50)
    obs, _ = env.reset(seed=3)
    assert obs.shape == (20,) and env.observation_space.contains(obs)
    np.testing.assert_array_equal(obs[15:], env.goal_colors)
    again = ChemicalMatchEnv(graph="full", num_objects=5).reset(seed=3)[0]
    np.testing.assert_array_equal(obs, again)
    goals = {tuple(env.reset(seed=s)[0][15:]) for s in range(20)}
    starts_equal_goal = [np.array_equal(o[:15:3], o[15:]) for o in (env.reset(seed=s)[0] for s in range(20))]
    assert len(goals) > 10 and not all(starts_equal_goal)
    for t in range(50):
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        np.testing.assert_array_equal(obs[15:], env.goal_colors)
        assert not terminated and truncated == (t == 49)


def test_reward_is_the_fraction_of_objects_at_their_goal_colour() -> None:
    env = ChemicalMatchEnv(graph="collider", num_objects=3, num_colors=4)
    env.reset(seed=0)
    goal = np.array([1, 2, 3])
    env.set_state(np.array([1, 0, 0, 0, 0, 0, 3, 0, 0, *goal], dtype=np.float32))
    _, reward, *_ = env.step(2 * 4 + 3)  # the collider object 2 has no descendants: only it changes
    assert reward == pytest.approx(2 / 3)
    _, reward, *_ = env.step(1 * 4 + 2)  # object 1 -> 2 re-samples object 2
    obs = env._observation()  # noqa: SLF001
    assert reward == pytest.approx(np.mean(obs[0:9:3] == goal)) == env.match_fraction(obs)
    rng = np.random.default_rng(0)
    for _ in range(50):
        obs, reward, *_ = env.step(int(rng.integers(12)))
        assert reward == env.match_fraction(obs)
    with pytest.raises(ValueError, match="goal colours"):
        env.set_state(np.array([1, 0, 0, 0, 0, 0, 3, 0, 0, 1, 2, 4], dtype=np.float32))


def test_spec_graphs_and_ood_passthrough() -> None:
    env = ChemicalMatchEnv(graph="chain", num_objects=3, ood_noise_scale=50.0, goal_interventions=2)
    spec = env.env_spec()
    assert spec.env_id == "chemical-match" and spec.num_factors == 12 and spec.state_dim == 12
    assert spec.factor_names[9:] == ("obj0.goal_color", "obj1.goal_color", "obj2.goal_color")
    assert decode(encode(spec), EnvSpec).factor_kinds[9:] == ("categorical",) * 3
    graph = env.global_graph
    assert graph.shape == (12, 13) and graph[9:, 9:12].tolist() == np.eye(3, dtype=int).tolist()
    assert not graph[9:, :9].any() and not graph[9:, 12].any() and not graph[:9, 9:12].any()
    obs, _ = env.reset(seed=0)
    _, _, _, _, info = env.step(0)
    assert info["local_graph"].shape == (12, 13)
    assert np.abs(obs[1:9:3]).max() > 1.0  # positions drawn at the OOD scale
    assert '"goal_interventions": 2' in spec.config_json
    nxt = env.sample_next_states(obs[None], 0)
    np.testing.assert_array_equal(nxt[0, 9:], obs[9:])


def test_with_goal_factors_keeps_the_action_column_last() -> None:
    graph = np.array([[1, 0, 1], [1, 1, 0]], dtype=np.uint8)
    out = with_goal_factors(graph, 1)
    assert out.tolist() == [[1, 0, 0, 1], [1, 1, 0, 0], [0, 0, 1, 0]]
