"""Which object each slot holds, so that slot ``k`` is one object in every frame (issue 24, item 5).

Slot attention orders its slots freely in each frame (the order the annealed mask prior teaches is
lost once the masks are dropped: results.md, Table 7.1's slot identity). A causal model over slots
needs slot ``k`` to be the same object at t and t + 1, and a graph over slots means something only
when slot ``k`` is the same object in every frame. So, once the slots are frozen:

1. **Targets from the masks** (training frames only): each slot's object is the one its decoder mask
   (alpha) overlaps most, a maximum-overlap one-to-one assignment of the K slots to the K segments
   (the background and each object) of the renderer's label map.
2. **An identity head**: a linear softmax classifier from a slot's vector to its object, fitted on
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
from scipy.optimize import linear_sum_assignment

from causal.slots import FEATURE_STRIDE

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
    """Each slot's object from the masks: the maximum-overlap assignment of the slots' alpha masks
    ``[B, K, n]`` to the segments of the label maps ``[B, H, W]``; long ``[B, K]``."""
    fractions = segment_fractions(labels, alpha.shape[1])
    return best_assignment(alpha @ fractions.transpose(1, 2))


def matching_accuracy(assigned: torch.Tensor, targets: torch.Tensor) -> dict[str, float]:
    """How often slots get the object their mask holds: per slot, and per frame (every slot right)."""
    right = assigned == targets
    return {"slot_accuracy": float(right.float().mean()), "frame_accuracy": float(right.all(dim=1).float().mean())}


class SlotIdentity:
    """A linear softmax head from a slot's vector ``[d]`` to its object (K classes), on standardised inputs."""

    def __init__(self, slot_dim: int, num_objects: int, seed: int = 0) -> None:
        generator = torch.Generator().manual_seed(seed)
        self.weight = torch.randn(num_objects, slot_dim, generator=generator) * 0.01
        self.bias = torch.zeros(num_objects)
        self.loc, self.scale = torch.zeros(slot_dim), torch.ones(slot_dim)

    def fit(self, slots: torch.Tensor, targets: torch.Tensor, steps: int = 300, lr: float = 0.05,
            weight_decay: float = 1e-4) -> float:
        """Fit on slots ``[B, K, d]`` and their objects ``[B, K]`` (full-batch Adam); the last loss."""
        flat, labels = slots.reshape(-1, slots.shape[-1]).double(), targets.reshape(-1)
        self.loc = flat.mean(0).float()
        self.scale = flat.std(0).clamp_min(1e-6).float()
        x = (flat.float() - self.loc) / self.scale
        weight, bias = self.weight.clone().requires_grad_(True), self.bias.clone().requires_grad_(True)
        optimizer = torch.optim.Adam([weight, bias], lr=lr, weight_decay=weight_decay)
        loss = torch.zeros(())
        for _ in range(steps):
            loss = F.cross_entropy(x @ weight.T + bias, labels)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        self.weight, self.bias = weight.detach(), bias.detach()
        return float(loss.detach())

    def log_probs(self, slots: torch.Tensor) -> torch.Tensor:
        """``[B, K, K]``: log p(object m | slot k)."""
        return F.log_softmax(((slots - self.loc) / self.scale) @ self.weight.T + self.bias, dim=-1)

    def assign(self, slots: torch.Tensor) -> torch.Tensor:
        """Each slot's object ``[B, K]``, one object per slot (the most probable joint assignment)."""
        return best_assignment(self.log_probs(slots))

    def order(self, slots: torch.Tensor) -> torch.Tensor:
        """Slots ``[B, K, d]`` in object order: position ``m`` holds the slot assigned object ``m``."""
        assigned = self.assign(slots)
        return torch.gather(slots, 1, assigned.argsort(dim=1)[..., None].expand_as(slots))

    def state_dict(self) -> dict[str, list]:
        return {k: getattr(self, k).tolist() for k in ("weight", "bias", "loc", "scale")}

    def load_state_dict(self, state: dict[str, list]) -> None:
        for k in ("weight", "bias", "loc", "scale"):
            setattr(self, k, torch.tensor(state[k], dtype=torch.float32))


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
