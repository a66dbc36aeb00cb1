"""Chemical rendered to pixels: seeding, shapes, masks that partition the frame, colours and positions
that follow the state, the registry entry and the gymnasium contract."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from envs import make_env
from envs.chemical_pixels import PALETTE, PART_COLOR, ChemicalPixelsEnv, masks_from_labels


def _env(**kwargs: object) -> ChemicalPixelsEnv:
    return ChemicalPixelsEnv(**{"graph": "chain", "num_objects": 5, **kwargs})


def test_seeded_episodes_repeat_frame_for_frame() -> None:
    runs = []
    for _ in range(2):
        env = _env()
        _, info = env.reset(seed=3)
        frames = [info["frame"]] + [env.step(a)[4]["frame"] for a in (0, 7, 13)]
        runs.append(np.stack(frames))
    np.testing.assert_array_equal(runs[0], runs[1])
    other = _env()
    assert not np.array_equal(other.reset(seed=4)[1]["frame"], runs[0][0])


@pytest.mark.parametrize("size", [32, 48])
def test_frame_and_mask_shapes(size: int) -> None:
    env = _env(frame_size=size, num_objects=4)
    _, info = env.reset(seed=0)
    assert info["frame"].shape == (size, size, 3) and info["frame"].dtype == np.uint8
    assert info["masks"].shape == (5, size, size) and info["masks"].dtype == bool
    _, _, _, _, info = env.step(0)
    assert info["masks"].shape == (5, size, size) and "local_graph" in info


def test_masks_partition_the_frame_and_every_object_is_visible() -> None:
    env = _env(num_objects=9)
    states = env.sample_next_states(np.tile(env.reset(seed=1)[0], (64, 1)), action=2)
    _, labels = env.render_states(states)
    masks = masks_from_labels(labels, env.num_objects)
    np.testing.assert_array_equal(masks.sum(axis=1), 1)
    assert (masks[:, 1:].sum(axis=(2, 3)) >= 4).all()


def test_colours_follow_the_state_and_background_is_black() -> None:
    env = _env()
    obs, info = env.reset(seed=2)
    frame, masks = info["frame"], info["masks"]
    np.testing.assert_array_equal(frame[masks[0]], 0)
    for k in range(env.num_objects):
        np.testing.assert_array_equal(frame[masks[1 + k]], np.broadcast_to(PALETTE[int(obs[3 * k])], (masks[1 + k].sum(), 3)))
    recoloured = obs.copy()
    recoloured[0] = (obs[0] + 1) % env.num_colors
    frames, _ = env.render_states(recoloured[None])
    assert (frames[0][masks[1]] == PALETTE[int(recoloured[0])]).all()


def test_two_tone_shapes_are_grey_below_their_centre_and_keep_their_masks() -> None:
    plain, two_tone = _env(frame_size=48), _env(frame_size=48, two_tone=True)
    plain.reset(seed=6)
    states = plain.sample_states(3)
    frames, labels = plain.render_states(states)
    toned, toned_labels = two_tone.render_states(states)
    np.testing.assert_array_equal(toned_labels, labels)
    rows = np.arange(48)[None, :, None] + 0.5
    for k in range(plain.num_objects):
        below = rows > (states[:, 3 * k + 2, None, None] + 1.0) * 24.0
        part = (labels == k + 1) & below
        assert part.any() and ((labels == k + 1) & ~below).any()
        np.testing.assert_array_equal(toned[part], np.broadcast_to(PART_COLOR, (part.sum(), 3)))
        np.testing.assert_array_equal(toned[(labels == k + 1) & ~below], frames[(labels == k + 1) & ~below])
    np.testing.assert_array_equal(toned[labels == 0], 0)
    assert two_tone.config()["two_tone"] is True and plain.config()["two_tone"] is False
    assert not (PALETTE == PART_COLOR).all(axis=1).any()


def test_shapes_sit_at_the_objects_positions() -> None:
    env = _env(frame_size=48)
    obs, info = env.reset(seed=5)
    for k in range(env.num_objects):
        ys, xs = np.nonzero(info["masks"][1 + k])
        centre = (np.array([xs.mean(), ys.mean()]) + 0.5) / 24.0 - 1.0
        np.testing.assert_allclose(centre, obs[3 * k + 1 : 3 * k + 3], atol=3.0 / 24.0)
    assert np.all(np.abs(obs.reshape(-1, 3)[:, 1:]) < 1.0)


def test_dynamics_and_truth_are_chemicals() -> None:
    env, plain = _env(), make_env("chemical", graph="chain", num_objects=5)
    np.testing.assert_array_equal(env.global_graph, plain.global_graph)
    env.reset(seed=0)
    _, _, _, _, info = env.step(7)
    np.testing.assert_array_equal(info["local_graph"], plain._local_graphs[1])
    assert env.env_spec().env_id == "chemical-pixels"
    assert ChemicalPixelsEnv(**{k: v for k, v in env.config().items() if k != "edges"},
                             graph="chain").config() == env.config()


def test_registry_builds_it_and_render_returns_the_frame() -> None:
    env = make_env("chemical-pixels", graph="chain", num_objects=4, render_mode="rgb_array")
    _, info = env.reset(seed=0)
    np.testing.assert_array_equal(env.render(), info["frame"])


def test_the_two_tone_entry_draws_what_two_tone_true_draws() -> None:
    entry = make_env("chemical-pixels-two-tone", graph="chain", num_objects=4)
    flagged = _env(num_objects=4, two_tone=True)
    frames = [env.reset(seed=3)[1]["frame"] for env in (entry, flagged)]
    np.testing.assert_array_equal(frames[0], frames[1])
    assert entry.config() == flagged.config() and (frames[0] == PART_COLOR).all(axis=-1).any()


def test_bad_options_are_refused() -> None:
    with pytest.raises(ValueError, match="ood_noise_scale"):
        _env(ood_noise_scale=0.1)
    with pytest.raises(ValueError, match="frame_size"):
        _env(num_objects=10, frame_size=12)
    with pytest.raises(ValueError, match="colours"):
        _env(num_colors=11)


def test_gymnasium_check_env() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(_env(), skip_render_check=True)
