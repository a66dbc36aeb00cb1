"""The slot identity head: the assignment is the best one-to-one, targets follow the masks, and a head
fitted on shuffled slots puts unseen frames' slots back in object order."""
from __future__ import annotations

import itertools

import pytest
import torch

from causal.slot_identity import (SlotIdentity, best_assignment, fit_identity, mask_targets, matching_accuracy,
                                  segment_fractions)


def _brute_force_total(scores: torch.Tensor) -> torch.Tensor:
    k = scores.shape[1]
    return torch.tensor([max(sum(float(m[i, p[i]]) for i in range(k)) for p in itertools.permutations(range(k)))
                         for m in scores], dtype=torch.float64)


@pytest.mark.parametrize("k", [1, 3, 5, 8])
def test_assignment_is_one_to_one_and_best(k: int) -> None:
    """Both paths (every permutation up to 7, Hungarian above) find the largest total score."""
    generator = torch.Generator().manual_seed(k)
    scores = torch.randn(6 if k < 8 else 2, k, k, generator=generator, dtype=torch.float64)
    assigned = best_assignment(scores)
    assert (assigned.sort(dim=1).values == torch.arange(k)).all()
    total = scores.gather(2, assigned[..., None]).squeeze(-1).sum(1)
    assert torch.allclose(total, _brute_force_total(scores), rtol=1e-12, atol=1e-12)


def test_targets_follow_the_masks() -> None:
    """A 8x8 frame, 2x2 tokens: the slot whose alpha covers object 1's pixels gets object 1."""
    labels = torch.zeros(1, 8, 8, dtype=torch.long)
    labels[0, :4, :4] = 1
    labels[0, 4:, 4:] = 2
    fractions = segment_fractions(labels, 3)
    assert fractions.shape == (1, 3, 4) and torch.allclose(fractions.sum(1), torch.ones(1, 4))
    alpha = fractions[:, [2, 0, 1]]  # slot 0 holds object 2, slot 1 the background, slot 2 object 1
    assert mask_targets(alpha, labels).tolist() == [[2, 0, 1]]
    assert matching_accuracy(torch.tensor([[2, 1, 0]]), torch.tensor([[2, 0, 1]])) == {
        "slot_accuracy": pytest.approx(1 / 3), "frame_accuracy": 0.0}


def test_head_orders_shuffled_slots_by_object() -> None:
    """Slots are an object's code plus noise (and a nuisance dimension), in a random order per frame."""
    generator = torch.Generator().manual_seed(0)
    k, d, frames = 4, 6, 400
    codes = torch.randn(k, d, generator=generator) * 2.0
    slots = codes[None] + 0.3 * torch.randn(frames, k, d, generator=generator)
    slots[..., -1] = 5.0 * torch.randn(frames, k, generator=generator)
    perm = torch.stack([torch.randperm(k, generator=generator) for _ in range(frames)])
    shuffled = torch.gather(slots, 1, perm[..., None].expand_as(slots))
    head = SlotIdentity(d, k)
    head.fit(shuffled[:300], perm[:300])
    assert matching_accuracy(head.assign(shuffled[300:]), perm[300:])["frame_accuracy"] == 1.0
    assert torch.equal(head.order(shuffled[300:])[0], slots[300:])
    state = head.state_dict()
    assert all(isinstance(v, torch.Tensor) for v in state.values())  # a checkpoint loads it with weights_only
    restored = SlotIdentity(d, k, seed=5)
    restored.load_state_dict(head.state_dict())
    assert torch.equal(restored.assign(shuffled), head.assign(shuffled))


def test_fit_identity_scores_held_out_frames_and_refuses_bad_input() -> None:
    generator = torch.Generator().manual_seed(1)
    labels = torch.zeros(10, 8, 8, dtype=torch.long)
    labels[:, :4] = 1
    slots = torch.randn(10, 2, 3, generator=generator)
    alpha = segment_fractions(labels, 2)
    head, scores = fit_identity(slots, alpha, labels, held_out=0.2)
    assert scores["fit_frames"] == 8 and scores["held_out_frames"] == 2 and 0 <= scores["slot_accuracy"] <= 1
    with pytest.raises(ValueError, match="held_out"):
        fit_identity(slots, alpha, labels, held_out=1.0)
    with pytest.raises(ValueError, match="at least 2 frames"):
        fit_identity(slots[:1], alpha[:1], labels[:1])
