"""Which object each slot holds, so that slot ``k`` is one object in every frame (issue 24, item 5).

Slot attention orders its slots freely in each frame (the order the annealed mask prior teaches is
lost once the masks are dropped: results.md, Table 7.1's slot identity). A causal model over slots
needs slot ``k`` to be the same object at t and t + 1, and a graph over slots means something only
when slot ``k`` is the same object in every frame. So, once the slots are frozen:

1. **Targets from the masks** (training frames only): each slot's object is the segment its decoder
   mask (alpha) covers most of, a one-to-one assignment of the K slots to the K segments (the
   background and each object) of the renderer's label map.
2. **An identity head**: a small MLP classifier from a slot's vector to its object, fitted on
   those targets. Objects differ in what a slot encodes of them (in ``chemical-pixels`` each object has
   its own shape; colour and position vary).
3. **Inference without masks**: each frame's slots are put in object order by the most probable
   one-to-one assignment under the head (:func:`best_assignment`), so no frame can give two slots the
   same object. The renderer's masks are never used at inference; they only score the head
   (:func:`matching_accuracy`).

The chapter has no such step: Dyn-O's world model is permutation-equivariant and its slots never need
names. Here CDL learns a graph over factors, which needs them (docs/deviations.md, Dyn-O).
"""
from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F
from torch import nn
from scipy.optimize import linear_sum_assignment

from causal.slots import FEATURE_STRIDE

HIDDEN = 64
"""Width of the identity head's two hidden layers."""

EXACT_UP_TO = 7
"""K up to which :func:`best_assignment` scores every permutation in one tensor op (7! = 5,040);
above, one Hungarian solve per frame."""


def best_assignment(scores: torch.Tensor) -> torch.Tensor:
    """The one-to-one assignment of rows to columns with the largest total score, per frame.

    ``scores`` ``[B, K, K]`` (slot k, object m); returns long ``[B, K]``: the object of each slot."""
    count, k = scores.shape[0], scores.shape[1]
    if k <= EXACT_UP_TO:
        perms = torch.tensor(list(itertools.permutations(range(k))), dtype=torch.long)  # [P, K]
        totals = scores[:, torch.arange(k), perms].sum(-1)  # [B, P]
        return perms[totals.argmax(dim=1)]
    out = torch.empty(count, k, dtype=torch.long)
    for b, matrix in enumerate(scores.detach().numpy()):
        rows, cols = linear_sum_assignment(-matrix)
        out[b, torch.from_numpy(rows)] = torch.from_numpy(cols)
    return out


def segment_fractions(labels: torch.Tensor, num_segments: int, stride: int = FEATURE_STRIDE) -> torch.Tensor:
    """float ``[B, K, n]``: the share of each feature token's ``stride`` x ``stride`` pixels in each
    segment of the label maps ``[B, H, W]`` (the resolution the slot decoder's alpha masks have)."""
    onehot = F.one_hot(labels.long(), num_segments).permute(0, 3, 1, 2).float()
    return F.avg_pool2d(onehot, stride).flatten(2)


def mask_targets(alpha: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Each slot's object from the masks: the one-to-one assignment of the slots' alpha masks ``[B, K, n]``
    to the segments of the label maps ``[B, H, W]`` that covers the largest total share of each segment;
    long ``[B, K]``. Shares, not pixel counts: slot attention spreads the background over every slot,
    and by counts the background would outweigh each slot's own object (it did, on a run's slots)."""
    fractions = segment_fractions(labels, alpha.shape[1])
    covered = (alpha @ fractions.transpose(1, 2)) / fractions.sum(-1).clamp_min(1e-6)[:, None, :]
    return best_assignment(covered)


def matching_accuracy(assigned: torch.Tensor, targets: torch.Tensor) -> dict[str, float]:
    """How often slots get the object their mask holds: per slot, and per frame (every slot right)."""
    right = assigned == targets
    return {"slot_accuracy": float(right.float().mean()), "frame_accuracy": float(right.all(dim=1).float().mean())}


class SlotIdentity:
    """A small MLP from a slot's vector ``[d]`` to its object (K classes), on standardised inputs.

    A linear head was tried first: on one run's frozen slots (4,096 frames, the last fifth held out) it
    matched 0.53 (pixel-count targets) to 0.61 (:func:`mask_targets`) of held-out slots, this MLP 0.76
    to 0.84: what tells the objects apart, their shape, is not linear in the slot vector."""

    def __init__(self, slot_dim: int, num_objects: int, seed: int = 0, hidden: int = HIDDEN) -> None:
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            self.net = nn.Sequential(nn.Linear(slot_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                     nn.Linear(hidden, num_objects))
        self.net.requires_grad_(False)
        self.loc, self.scale = torch.zeros(slot_dim), torch.ones(slot_dim)

    def fit(self, slots: torch.Tensor, targets: torch.Tensor, steps: int = 1000, lr: float = 3e-3) -> float:
        """Fit on slots ``[B, K, d]`` and their objects ``[B, K]`` (full-batch Adam); the last loss."""
        flat, labels = slots.reshape(-1, slots.shape[-1]), targets.reshape(-1)
        self.loc, self.scale = flat.mean(0), flat.std(0).clamp_min(1e-6)
        x = (flat - self.loc) / self.scale
        self.net.requires_grad_(True)
        optimizer = torch.optim.Adam(self.net.parameters(), lr=lr)
        loss = torch.zeros(())
        for _ in range(steps):
            loss = F.cross_entropy(self.net(x), labels)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        self.net.requires_grad_(False)
        return float(loss.detach())

    def log_probs(self, slots: torch.Tensor) -> torch.Tensor:
        """``[B, K, K]``: log p(object m | slot k)."""
        return F.log_softmax(self.net((slots - self.loc) / self.scale), dim=-1)

    def assign(self, slots: torch.Tensor) -> torch.Tensor:
        """Each slot's object ``[B, K]``, one object per slot (the most probable joint assignment)."""
        return best_assignment(self.log_probs(slots))

    def order(self, slots: torch.Tensor, *per_slot: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Slots ``[B, K, d]`` in object order (position ``m`` holds the slot assigned object ``m``), and
        any other per-slot tensors ``[B, K, ...]`` (their masks) in the same order."""
        order = self.assign(slots).argsort(dim=1)
        return tuple(torch.gather(x, 1, order[..., None].expand_as(x)) for x in (slots, *per_slot))

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {**{f"net.{k}": v.clone() for k, v in self.net.state_dict().items()}, "loc": self.loc.clone(),
                "scale": self.scale.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.net.load_state_dict({k[len("net."):]: v for k, v in state.items() if k.startswith("net.")})
        self.loc, self.scale = state["loc"].clone(), state["scale"].clone()


def fit_identity(slots: torch.Tensor, alpha: torch.Tensor, labels: torch.Tensor, held_out: float = 0.2,
                 seed: int = 0) -> tuple[SlotIdentity, dict[str, float]]:
    """An identity head fitted on the first ``1 - held_out`` of the frames (slots ``[B, K, d]``, their
    alpha masks ``[B, K, n]`` and label maps ``[B, H, W]``), scored on the rest; the head and its
    held-out matching accuracy (``slot_accuracy``, ``frame_accuracy``, the frames it was fitted on)."""
    if not 0.0 < held_out < 1.0:
        raise ValueError(f"held_out must be in (0, 1), got {held_out}")
    if len(slots) < 2:
        raise ValueError(f"an identity head needs at least 2 frames, got {len(slots)}")
    targets = mask_targets(alpha, labels)
    split = max(1, min(len(slots) - 1, int(round(len(slots) * (1.0 - held_out)))))
    head = SlotIdentity(slots.shape[-1], slots.shape[1], seed)
    loss = head.fit(slots[:split], targets[:split])
    scores = matching_accuracy(head.assign(slots[split:]), targets[split:])
    return head, {**scores, "fit_loss": loss, "fit_frames": float(split), "held_out_frames": float(len(slots) - split)}
