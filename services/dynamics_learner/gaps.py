"""Transitions lost on the way to the learner, counted from the gaps in each worker's ``seq``.

Every TransitionBatch carries ``(worker_id, seq)``; a worker numbers its batches 0, 1, 2, ... in each
life (a restarted worker counts from 0 again, and its life is told by its episode ids:
``TransitionBatch.life``). A batch whose ``seq`` is past the next one expected from its life marks
the batches between as lost; one of those arriving later (reordered) is taken back off the count; a
``seq`` already taken is a duplicate and counts nothing. Zenoh drops what a slow subscriber cannot
take without telling anyone, so this is the only place the loss shows. No bus."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

MISSING_KEPT = 4096
"""Missing ``seq`` values remembered per life (the newest): a batch arriving later than this many
batches after its successors stays counted as lost (and is then taken as a duplicate)."""


@dataclass
class _Life:
    next_seq: int = 0
    """One past the highest ``seq`` taken from this life."""
    missing: dict[int, int] = field(default_factory=dict)
    """``seq`` skipped and not (yet) arrived -> the steps counted lost for it, in ascending ``seq`` order
    (each gap lies above every earlier one)."""


class SeqGaps:
    """Counts batches and steps lost per worker life from ``seq`` gaps.

    A lost batch's steps are not known; they are counted as the length of the batch that revealed
    the gap (a worker publishes batches of one length, ``--worker-batch-steps``). Loss at the tail of
    a life (batches published and dropped just before a worker died) shows no gap and is not counted;
    nor are batches not yet published (a killed worker's unfinished batch)."""

    def __init__(self) -> None:
        self.lives: dict[tuple[str, int], _Life] = {}
        self.lost_batches = 0
        self.lost_steps = 0
        self.late = 0
        """Batches taken off the lost count because they arrived after a successor (reordered)."""
        self.duplicates = 0

    def observe(self, worker_id: str, life: int, seq: int, steps: int) -> str:
        """Take batch ``seq`` (``steps`` long) of ``worker_id``'s life ``life``; returns what it was:
        ``"next"`` (in order), ``"after_gap"`` (batches before it are missing), ``"late"`` (a missing
        one arriving) or ``"duplicate"``."""
        state = self.lives.setdefault((worker_id, life), _Life())
        if seq >= state.next_seq:
            gap = seq - state.next_seq
            self.lost_batches += gap
            self.lost_steps += gap * steps
            state.missing.update((s, steps) for s in range(max(state.next_seq, seq - MISSING_KEPT), seq))
            while len(state.missing) > MISSING_KEPT:  # keys go in ascending, so the first is the oldest
                del state.missing[next(iter(state.missing))]
            state.next_seq = seq + 1
            return "after_gap" if gap else "next"
        counted = state.missing.pop(seq, None)
        if counted is None:
            self.duplicates += 1
            return "duplicate"
        self.lost_batches -= 1
        self.lost_steps -= counted
        self.late += 1
        return "late"

    def stats(self) -> dict[str, float]:
        """The counts for the learner's stats beat."""
        return {"lost_batches": self.lost_batches, "lost_steps": self.lost_steps,
                "late_batches": self.late, "duplicate_batches": self.duplicates}

    def state_dict(self) -> dict[str, Any]:
        """Plain values only (a checkpoint loads with ``weights_only``)."""
        return {"lives": [[worker, life, s.next_seq, sorted(s.missing.items())]
                          for (worker, life), s in self.lives.items()],
                "lost_batches": self.lost_batches, "lost_steps": self.lost_steps,
                "late": self.late, "duplicates": self.duplicates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.lives = {(str(worker), int(life)): _Life(int(next_seq), {int(s): int(n) for s, n in missing})
                      for worker, life, next_seq, missing in state["lives"]}
        self.lost_batches, self.lost_steps = int(state["lost_batches"]), int(state["lost_steps"])
        self.late, self.duplicates = int(state["late"]), int(state["duplicates"])
