"""Dyn-O's slot representation (eq. 7.1): the mask-drop schedule, the mask prior in slot attention,
shapes, batching, what is trained and what is frozen, and seeded reproducibility."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from causal.slots import (
    SlotAttention,
    SlotConfig,
    SlotModel,
    SlotTrainer,
    drop_probability,
    fit_autoencoder,
    token_masks,
)
from envs.chemical_pixels import ChemicalPixelsEnv

torch.set_num_threads(1)
SMALL = SlotConfig(num_slots=5, feature_dim=8, slot_dim=16, attention_dim=16, decoder_hidden=16, batch_size=4)


def _frames(count: int = 8, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    env = ChemicalPixelsEnv(graph="chain", num_objects=4, frame_size=16)
    env.reset(seed=seed)
    frames, labels = env.render_states(env.sample_states(count))
    return torch.from_numpy(frames), torch.from_numpy(labels.astype(np.int64))


def test_drop_probability_follows_the_log_schedule() -> None:
    assert drop_probability(0, 1000) == 0.0
    assert drop_probability(1000, 1000) == pytest.approx(1.0)
    assert drop_probability(99, 9999) == pytest.approx(math.log(100) / math.log(10000), rel=1e-12)
    values = [drop_probability(u, 500) for u in range(501)]
    assert all(b >= a for a, b in zip(values, values[1:]))


def test_spare_slots_take_nothing_under_the_masks() -> None:
    """K above the segments (the chapter's 31 or 47 slots): the spare slots have no token under the
    mask prior, so slot attention gives them no attention at all; without masks they compete."""
    frames, labels = _frames(4)
    config = dataclasses.replace(SMALL, num_slots=8)
    allowed = token_masks(labels, config.num_slots)
    assert not allowed[:, 5:].any() and allowed.any(dim=1).all()
    torch.manual_seed(0)
    model = SlotModel(config, frame_size=16)
    masked = model(frames, allowed).attention
    assert masked[:, 5:].abs().max() == 0.0
    assert torch.allclose(masked.sum(dim=1), torch.ones(4, masked.shape[2]), rtol=1e-6, atol=1e-6)
    assert model(frames).attention[:, 5:].amin() > 0.0


def test_token_masks_cover_every_token_and_mark_each_segment() -> None:
    labels = torch.zeros(1, 8, 8, dtype=torch.long)
    labels[0, :4, :4] = 1
    labels[0, 5, 6] = 2
    allowed = token_masks(labels, num_slots=3, stride=4).view(1, 3, 2, 2)
    assert allowed.any(dim=1).all()
    assert allowed[0, 1].tolist() == [[True, False], [False, False]]
    assert allowed[0, 2].tolist() == [[False, False], [False, True]]
    assert allowed[0, 0].tolist() == [[False, True], [True, True]]
    with pytest.raises(ValueError, match="slots"):
        token_masks(labels, num_slots=2, stride=4)


def test_objects_rule_gives_a_token_an_object_touches_to_its_objects_only() -> None:
    labels = torch.zeros(1, 8, 8, dtype=torch.long)
    labels[0, :4, :4] = 1  # fills the top-left token
    labels[0, 5, 6] = 2  # one pixel of the bottom-right token, the rest background
    labels[0, 1, 5] = 1  # one pixel of object 1 and one of object 2 in the top-right token
    labels[0, 2, 6] = 2
    allowed = token_masks(labels, num_slots=3, stride=4, rule="objects").view(1, 3, 2, 2)
    assert allowed.any(dim=1).all()
    assert allowed[0, 0].tolist() == [[False, False], [True, False]]  # the background: the untouched token only
    assert allowed[0, 1].tolist() == [[True, True], [False, False]]
    assert allowed[0, 2].tolist() == [[False, True], [False, True]]
    touch = token_masks(labels, num_slots=3, stride=4).view(1, 3, 2, 2)
    assert torch.equal(touch[0, 1:], allowed[0, 1:]) and touch[0, 0].tolist() == [[False, True], [True, True]]
    with pytest.raises(ValueError, match="rule"):
        token_masks(labels, num_slots=3, stride=4, rule="majority")
    with pytest.raises(ValueError, match="token_mask"):
        SlotConfig(token_mask="majority")


def test_slot_attention_respects_the_mask_prior_and_is_batched() -> None:
    torch.manual_seed(0)
    attention = SlotAttention(8, SMALL)
    tokens = torch.randn(3, 10, 8)
    allowed = torch.rand(3, SMALL.num_slots, 10) < 0.5
    allowed[:, 0] |= ~allowed.any(dim=1)
    slots, weights = attention(tokens, allowed)
    assert slots.shape == (3, SMALL.num_slots, SMALL.slot_dim) and weights.shape == (3, SMALL.num_slots, 10)
    assert float(weights.detach()[~allowed].abs().max()) < 1e-6
    torch.testing.assert_close(weights.sum(dim=1), torch.ones(3, 10))
    one, _ = attention(tokens[1:2], allowed[1:2])
    torch.testing.assert_close(one[0], slots[1], rtol=1e-5, atol=1e-5)


def test_model_shapes_alpha_masks_and_segmentation() -> None:
    torch.manual_seed(0)
    model = SlotModel(SMALL, frame_size=16)
    frames, labels = _frames(4)
    out = model(frames, token_masks(labels, SMALL.num_slots))
    assert out.slots.shape == (4, 5, 16) and out.features.shape == (4, 16, 8)
    assert out.features_hat.shape == out.features.shape and out.reconstruction.shape == (4, 3, 16, 16)
    torch.testing.assert_close(out.alpha.sum(dim=1), torch.ones(4, 16))
    segments = model.segment(frames)
    assert segments.shape == (4, 16, 16) and int(segments.max()) < SMALL.num_slots


def test_training_moves_the_slots_and_leaves_the_frozen_autoencoder() -> None:
    torch.manual_seed(0)
    model = SlotModel(SMALL, frame_size=16)
    frames, labels = _frames(16)
    fit_autoencoder(model.autoencoder, frames, updates=2, batch_size=4)
    assert not any(p.requires_grad for p in model.autoencoder.parameters())
    before_ae = [p.clone() for p in model.autoencoder.parameters()]
    before_slots = [p.clone() for p in model.slot_parameters()]
    losses = SlotTrainer(model, total_updates=3).update(frames[:4], labels[:4])
    assert {"loss", "feature_mse", "image_mse"} <= set(losses) and np.isfinite(losses["loss"])
    assert all(torch.equal(a, b) for a, b in zip(before_ae, model.autoencoder.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(before_slots, model.slot_parameters()))


def test_mask_prior_modes() -> None:
    _, labels = _frames(64)
    allowed = token_masks(labels, SMALL.num_slots)
    model = SlotModel(SMALL, frame_size=16)
    annealed = SlotTrainer(model, total_updates=100)
    assert torch.equal(annealed.masks_for(labels), allowed)
    annealed.updates = 100
    assert annealed.masks_for(labels).all()
    annealed.updates = 10
    dropped = annealed.masks_for(labels).flatten(1).all(dim=1).float().mean()
    assert abs(float(dropped) - drop_probability(10, 100)) < 0.2
    none = SlotTrainer(SlotModel(dataclasses.replace(SMALL, mask_prior="none"), 16), 100)
    always = SlotTrainer(SlotModel(dataclasses.replace(SMALL, mask_prior="always"), 16), 100)
    always.updates = 100
    assert none.masks_for(labels) is None and torch.equal(always.masks_for(labels), allowed)
    with pytest.raises(ValueError, match="mask_prior"):
        SlotConfig(mask_prior="sometimes")


def test_seeded_training_repeats() -> None:
    frames, labels = _frames(8)
    runs = []
    for _ in range(2):
        torch.manual_seed(1)
        trainer = SlotTrainer(SlotModel(SMALL, frame_size=16), total_updates=4, seed=1)
        runs.append([trainer.update(frames[:4], labels[:4])["loss"] for _ in range(3)])
    assert runs[0] == runs[1]


def test_matched_masks_give_each_segment_to_the_slot_that_attends_to_it_most() -> None:
    """``mask_assignment="matched"``: each frame's segments are a permutation of its rows, the one
    that maximises the slots' unmasked attention on their segments (checked against every
    permutation), so the prior groups tokens without fixing which slot takes which object."""
    import itertools
    torch.manual_seed(0)
    model = SlotModel(dataclasses.replace(SMALL, mask_assignment="matched"), 16).eval()
    frames, labels = _frames(3)
    allowed = token_masks(labels, SMALL.num_slots)
    matched = model.match_segments(frames, allowed)
    with torch.no_grad():
        attention = model.slot_attention(model._tokens(frames)[1])[1]
    share = attention @ allowed.float().transpose(1, 2) / allowed.sum(-1).clamp_min(1)[:, None, :]
    for b in range(len(frames)):
        rows = [next(s for s in range(SMALL.num_slots) if torch.equal(matched[b, k], allowed[b, s]))
                for k in range(SMALL.num_slots)]
        assert sorted(rows) == list(range(SMALL.num_slots))  # a permutation of the segments
        best = max(sum(float(share[b, k, p[k]]) for k in range(SMALL.num_slots))
                   for p in itertools.permutations(range(SMALL.num_slots)))
        assert sum(float(share[b, k, rows[k]]) for k in range(SMALL.num_slots)) == pytest.approx(best, rel=1e-6)
    trainer = SlotTrainer(model, total_updates=100)
    assert torch.equal(trainer.masks_for(labels, frames), matched)  # update 0: no mask dropped
    with pytest.raises(ValueError, match="frames"):
        trainer.masks_for(labels)
    with pytest.raises(ValueError, match="mask_assignment"):
        dataclasses.replace(SMALL, mask_assignment="sorted")


def test_a_matched_update_encodes_the_frames_once_with_the_same_result() -> None:
    """The trainer's update shares the frames' tokens between the matching and the pass: the same
    loss as matching and passing separately, and one encoder call instead of two."""
    frames, labels = _frames(4)
    config = dataclasses.replace(SMALL, mask_assignment="matched")
    losses, calls = [], []
    for shared in (False, True):
        torch.manual_seed(2)
        model = SlotModel(config, 16)
        trainer = SlotTrainer(model, total_updates=10, seed=3)
        encoder_calls = []
        model.autoencoder.encoder.register_forward_hook(lambda *_: encoder_calls.append(1))
        if shared:
            losses.append(trainer.update(frames, labels)["loss"])
        else:  # the path before: match on its own encoding, then pass on another
            model.train()
            loss, _ = model.loss(frames, model(frames, trainer.masks_for(labels, frames)))
            losses.append(float(loss.detach()))
        calls.append(len(encoder_calls))
    assert losses[0] == pytest.approx(losses[1], rel=1e-6)
    assert calls == [2, 1]


def test_slot_attention_learns_to_bind_as_the_masks_do_only_with_the_binding_term() -> None:
    """Under one-slot-per-token masks the restricted attention is 1 whatever the logits, so only the
    binding term pulls the unmasked attention towards the masks' slots."""
    generator = torch.Generator().manual_seed(0)
    tokens = torch.randn(8, 12, 6, generator=generator)
    labels = (tokens[..., 0] > 0).long() + (tokens[..., 1] > 0.5).long()  # a token's segment: its look
    allowed = torch.nn.functional.one_hot(labels, 3).permute(0, 2, 1).bool()
    ends = []
    for weight in (0.0, 1.0):
        torch.manual_seed(0)
        attention = SlotAttention(6, SlotConfig(num_slots=3, slot_dim=8, attention_dim=8, iterations=2))
        optimizer = torch.optim.Adam(attention.parameters(), lr=1e-2)
        with torch.no_grad():
            start = float(attention.bind(tokens, allowed)[2])
        for _ in range(80):
            slots, _, binding = attention.bind(tokens, allowed)
            loss = slots.pow(2).mean() + weight * binding
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            ends.append(float(attention.bind(tokens, allowed)[2]))
            assert float(attention.bind(tokens)[2]) == 0.0
    assert ends[1] < 0.5 * start and ends[1] < 0.5 * ends[0]
    with pytest.raises(ValueError, match="mask_binding"):
        SlotConfig(mask_binding=-0.1)
