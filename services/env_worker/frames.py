"""The frames of an env-worker's steps, for the factor-extractor (``--worker-publish-frames``).

An env that renders puts its frame in ``info["frame"]`` (uint8 ``[H, W, 3]``) on reset and on every step,
and, where the renderer knows each pixel's object, ``info["masks"]`` (bool ``[N + 1, H, W]``, channel 0
the background): they become a FrameBatch's ``frames`` and ``labels``. Each distinct frame travels once
(step t's next observation is step t + 1's observation), so a batch of T steps carries T + 1 frames plus
one per episode reset inside it. ``stride`` keeps every ``stride``-th pixel along each side.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from proto.messages import FrameBatch, TransitionBatch


def has_frames(info: dict[str, Any]) -> bool:
    return isinstance(info.get("frame"), np.ndarray) and info["frame"].ndim == 3 and info["frame"].shape[2] == 3


class FrameRecorder:
    """Collects the frames of one batch of steps and packs them with the batch's TransitionBatch."""

    def __init__(self, reset_info: dict[str, Any], stride: int = 1, labels: bool = True) -> None:
        """``labels``: pack the frames' label maps where the env gives masks (the slot extractor's mask
        prior and identity head read them; the latent-action labeller does not, so frames sent beside
        transitions go without them: a quarter of their bytes at 32x32)."""
        if not has_frames(reset_info):
            raise ValueError("this environment renders no frames (info['frame'], uint8 [H, W, 3]): publishing "
                             "frames needs one that does (chemical-pixels)")
        self.stride, self.labels = stride, labels
        self.current = self._frame(reset_info)
        self.begin()

    def _frame(self, info: dict[str, Any]) -> tuple[np.ndarray, np.ndarray | None]:
        s = self.stride
        masks = info.get("masks") if self.labels else None
        labels = np.argmax(masks, axis=0).astype(np.uint8)[::s, ::s] if masks is not None else None
        return np.ascontiguousarray(info["frame"][::s, ::s]), labels

    def begin(self) -> None:
        """Start a batch from the current observation's frame."""
        self.frames: list[tuple[np.ndarray, np.ndarray | None]] = [self.current]
        self.state_index: list[int] = []
        self.next_index: list[int] = []
        self.at = 0

    def record(self, step_info: dict[str, Any], reset_info: dict[str, Any] | None) -> None:
        """One step: its next observation's frame, and the reset's frame where the episode ended."""
        self.state_index.append(self.at)
        self.frames.append(self._frame(step_info))
        self.next_index.append(len(self.frames) - 1)
        if reset_info is not None:
            self.frames.append(self._frame(reset_info))
        self.at = len(self.frames) - 1
        self.current = self.frames[-1]

    def pack(self, batch: TransitionBatch) -> FrameBatch:
        """The FrameBatch of ``batch``'s steps (the ones recorded since :meth:`begin`)."""
        if len(self.state_index) != len(batch):
            raise ValueError(f"{len(self.state_index)} steps recorded for a batch of {len(batch)}")
        frames = np.stack([f for f, _ in self.frames])
        labelled = all(lab is not None for _, lab in self.frames)
        labels = np.stack([lab for _, lab in self.frames]) if labelled else None
        return FrameBatch(worker_id=batch.worker_id, seq=batch.seq, policy_version=batch.policy_version,
                          frames=frames, state_frame=np.asarray(self.state_index, np.int32),
                          next_frame=np.asarray(self.next_index, np.int32), action=batch.action, reward=batch.reward,
                          terminated=batch.terminated, truncated=batch.truncated, episode_id=batch.episode_id,
                          step=batch.step, labels=labels)
