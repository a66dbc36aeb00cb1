"""factor-extractor core: frames in, slot factors out. No bus.

The extractor learns the slot representation itself (:class:`causal.slot_extractor.FrameSlotLearner`)
from the first frames it receives (held in a bounded replay, with the renderer's masks for the mask
prior), freezes it, fixes each slot's normalisation from the slots of the frames it holds, and from
then on turns every :class:`FrameBatch` into a :class:`TransitionBatch` whose state is the frame's
slots (K continuous factors of size d_xi, ``slot0`` .. ``slot{K-1}``). Frames that arrive before the
representation is frozen train it and are not published: no transition is ever in another factor space.
Why the extractor and not the Dyn-O learner trains the slots: docs/architecture.md (factor-extractor).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from causal.fg_ari import BOUND_FG_ARI, mean_fg_ari
from causal.skild import object_graphs
from causal.slot_extractor import FrameSlotLearner
from causal.slot_identity import SlotIdentity, fit_identity, mask_targets, matching_accuracy
from causal.slots import FEATURE_STRIDE
from proto.codec import ProtocolError
from proto.messages import EnvSpec, FrameBatch, TransitionBatch
from services.factor_extractor.config import FactorExtractorConfig
from services.runtime.checkpoint import check_fingerprint, load_checkpoint, save_checkpoint

SCALE_FLOOR = 1e-3
"""Smallest per-slot scale in the spec (a slot that never varies would otherwise divide by zero)."""


def slot_spec(env: EnvSpec, num_slots: int, slot_dim: int, locs: tuple[float, ...], scales: tuple[float, ...],
              by_object: bool = False) -> EnvSpec:
    """The spec of the slot factors: the env's action space and episodes, K continuous factors of size
    ``slot_dim``. Slots in object order (``by_object``, the identity head) are named ``background`` and the
    env's objects, and carry the env's object graph as truth (:func:`slot_graph`); otherwise ``slot0`` ..
    with no truth (which slot is which object changes from frame to frame)."""
    objects = tuple(dict.fromkeys(env.factor_objects))
    names = ("background",) + objects if by_object else tuple(f"slot{k}" for k in range(num_slots))
    config = {"env": env.env_id, "env_config": json.loads(env.config_json), "num_slots": num_slots, "slot_dim": slot_dim,
              "identity": "learned" if by_object else "none"}
    truth = slot_graph(env) if by_object and env.global_graph is not None else None
    return EnvSpec(env_id=f"{env.env_id}-slots", factor_names=names, factor_kinds=("continuous",) * num_slots,
                   factor_sizes=(slot_dim,) * num_slots, factor_objects=names, factor_locs=locs, factor_scales=scales,
                   action_kind=env.action_kind, action_size=env.action_size, episode_length=env.episode_length,
                   global_graph=truth, config_json=json.dumps(config, sort_keys=True))


def slot_graph(env: EnvSpec) -> np.ndarray:
    """uint8 ``[N + 1, N + 2]``: the env's graph over objects (one object depends on another when any of
    its factors depends on any of the other's) with the background first, which depends on nothing but
    itself (self-edges are assumed, as in every env's truth) and which nothing depends on."""
    objects = object_graphs(env.global_graph[None], env.factor_objects)[0]
    n = objects.shape[0]
    graph = np.zeros((n + 1, n + 2), dtype=np.uint8)
    graph[0, 0] = 1
    graph[1:, 1:] = objects
    return graph


class FrameReplay:
    """A bounded ring of frames (uint8 ``[N, H, W, 3]``) and their label maps (uint8 ``[N, H, W]``)."""

    def __init__(self, capacity: int, height: int, width: int, labelled: bool) -> None:
        self.frames = np.zeros((capacity, height, width, 3), np.uint8)
        self.labels = np.zeros((capacity, height, width), np.uint8) if labelled else None
        self.capacity, self.size, self.next = capacity, 0, 0

    def add(self, frames: np.ndarray, labels: np.ndarray | None) -> None:
        for start in range(0, len(frames), self.capacity):
            chunk = slice(start, start + self.capacity)
            rows = (self.next + np.arange(len(frames[chunk]))) % self.capacity
            self.frames[rows] = frames[chunk]
            if self.labels is not None:
                self.labels[rows] = labels[chunk]
            self.next = int(rows[-1] + 1) % self.capacity
            self.size = min(self.size + len(rows), self.capacity)

    def sample(self, count: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor | None]:
        rows = torch.randint(self.size, (count,), generator=generator).numpy()
        labels = torch.from_numpy(self.labels[rows].astype(np.int64)) if self.labels is not None else None
        return torch.from_numpy(self.frames[rows]), labels

    def newest(self, count: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The newest ``count`` frames held (newest first) and their label maps (None if unlabelled)."""
        rows = (self.next - 1 - np.arange(min(count, self.size))) % self.capacity
        return self.frames[rows], (self.labels[rows] if self.labels is not None else None)


class FactorExtractorCore:
    """Learns the slots from frames, then turns FrameBatches into TransitionBatches of slot factors."""

    def __init__(self, cfg: FactorExtractorConfig, env: EnvSpec) -> None:
        self.cfg, self.env = cfg, env
        self.num_objects = len(dict.fromkeys(env.factor_objects))
        self.slot_config = dataclasses.replace(cfg.slot, num_slots=cfg.num_slots or self.num_objects + 1)
        if cfg.identity == "learned" and self.slot_config.num_slots != self.num_objects + 1:
            raise ValueError(f"identity 'learned' names one slot per segment: num_slots must be {self.num_objects + 1} "
                             f"(the background and {self.num_objects} objects), got {self.slot_config.num_slots}")
        self.identity: SlotIdentity | None = None
        self.identity_scores: dict[str, float] = {}
        self.live_matching = np.zeros(4)  # slots right, slots scored, frames all right, frames scored
        self.learner: FrameSlotLearner | None = None
        self.replay: FrameReplay | None = None
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.locs: tuple[float, ...] | None = None
        self.scales: tuple[float, ...] | None = None
        self.frames_trained_on, self.batches_published, self.steps_published = 0, 0, 0
        self.last_stats: dict[str, float] = {}

    @property
    def ready(self) -> bool:
        """The representation is frozen and normalised: transitions can be published."""
        return self.learner is not None and self.learner.frozen and self.scales is not None

    @property
    def may_update(self) -> bool:
        return (self.learner is not None and not self.learner.frozen and self.replay is not None
                and self.replay.size >= self.cfg.warmup_frames)

    def ingest(self, batch: FrameBatch) -> TransitionBatch | None:
        """The batch as slot transitions once the slots are frozen; before, its frames train them (None).
        ``ProtocolError`` for frames that do not fit this extractor (size, labels)."""
        self._check(batch)
        if self.ready:
            return self.transitions(batch)
        if self.replay is None:
            _, height, width, _ = batch.frames.shape
            self.replay = FrameReplay(self.cfg.replay_frames, height, width, batch.labels is not None)
        self.replay.add(batch.frames, batch.labels)
        self.frames_trained_on += len(batch.frames)
        if self.learner.frozen:  # the identity head waits for its frames (or no updates were asked for)
            self._finish_when_held()
        return None

    def _check(self, batch: FrameBatch) -> None:
        size = batch.frames.shape[1]
        if batch.frames.shape[2] != size or size % FEATURE_STRIDE or size < 2 * FEATURE_STRIDE:
            raise ProtocolError("inconsistent", f"FrameBatch: frames {batch.frames.shape[1:3]}, want square, a "
                                                f"multiple of {FEATURE_STRIDE} and >= {2 * FEATURE_STRIDE}")
        if self.learner is None:
            self._build(size)
        if size != self.learner.frame_size:
            raise ProtocolError("inconsistent", f"FrameBatch: {size}-pixel frames, this extractor learned "
                                                f"{self.learner.frame_size}-pixel ones")
        needs_labels = (self.slot_config.mask_prior != "none" or self.cfg.identity == "learned") and not self.ready
        if needs_labels and batch.labels is None:
            raise ProtocolError("inconsistent", f"FrameBatch: no labels; mask prior {self.slot_config.mask_prior!r} and "
                                                f"identity {self.cfg.identity!r} need them while the slots are learned")
        if batch.labels is not None and int(batch.labels.max()) >= self.slot_config.num_slots:
            raise ProtocolError("inconsistent", f"FrameBatch.labels: object {int(batch.labels.max())} for "
                                                f"{self.slot_config.num_slots} slots")
        if self.replay is not None and (batch.labels is None) != (self.replay.labels is None) and not self.ready:
            raise ProtocolError("inconsistent", "FrameBatch: labels in some batches and not in others")

    def _build(self, frame_size: int) -> None:
        self.learner = FrameSlotLearner(self.slot_config, frame_size, self.cfg.ae_updates, self.cfg.slot_updates,
                                        self.cfg.ae_lr, self.cfg.seed)

    def train_step(self) -> dict[str, float]:
        """One update of the slot representation on frames from the replay; once it freezes, the per-slot
        normalisation is set from the newest frames held."""
        frames, labels = self.replay.sample(self.slot_config.batch_size, self.generator)
        self.last_stats = self.learner.update(frames, labels)
        if self.learner.frozen:
            self._finish_when_held()
        return self.last_stats

    def frames_needed(self) -> int:
        """Frames the replay must hold, once the slots froze, before the identity head is fitted and
        transitions are published (the warm-up's, or the head's ``identity_frames`` up to the replay's size)."""
        if self.cfg.identity != "learned":
            return self.cfg.warmup_frames
        return max(self.cfg.warmup_frames, min(self.cfg.identity_frames, self.cfg.replay_frames))

    def _finish_when_held(self) -> None:
        if self.replay is not None and self.replay.size >= self.frames_needed():
            self._freeze_outputs()

    def _freeze_outputs(self) -> None:
        """Once frozen: fit the identity head (if learned) on the newest frames held, then each published
        factor's loc and scale from the slots, in the order they will be published."""
        if self.cfg.identity == "learned":
            frames, labels = (x[::-1].copy() for x in self.replay.newest(self.cfg.identity_frames))  # oldest first
            slots, alpha = self.learner.encode_with_masks(torch.from_numpy(frames))
            self.identity, scores = fit_identity(slots, alpha, torch.from_numpy(labels), seed=self.cfg.seed)
            held_out = slice(int(scores["fit_frames"]), None)
            segments = self.learner.segment(torch.from_numpy(frames[held_out])).numpy()
            score = mean_fg_ari(labels[held_out], segments)
            self.identity_scores = {**scores, **({"fg_ari": score} if score is not None else {})}
            newest = slots[-min(self.cfg.statistics_frames, len(slots)):]  # already encoded: the statistics' frames
            slots = self.identity.order(newest)[0].numpy().astype(np.float64)
        else:
            slots = self.learner.encode(torch.from_numpy(self.replay.newest(self.cfg.statistics_frames)[0]))
            slots = slots.numpy().astype(np.float64)
        self.locs = tuple(float(x) for x in slots.mean(axis=(0, 2)))
        self.scales = tuple(max(float(x), SCALE_FLOOR) for x in slots.std(axis=(0, 2)))

    def _slots(self, frames: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Each frame's slots ``[B, K, d]``, in object order under the identity head, and their alpha masks
        in the same order."""
        slots, alpha = self.learner.encode_with_masks(torch.from_numpy(frames))
        return (slots, alpha) if self.identity is None else self.identity.order(slots, alpha)

    def spec(self) -> EnvSpec:
        """The spec of the published slot factors (only once :attr:`ready`)."""
        if not self.ready:
            raise RuntimeError("the slot representation is not frozen yet")
        return slot_spec(self.env, self.slot_config.num_slots, self.slot_config.slot_dim, self.locs, self.scales,
                         by_object=self.identity is not None)

    def transitions(self, batch: FrameBatch) -> TransitionBatch:
        """``batch`` with each step's observation and next observation replaced by their frames' slots."""
        ordered, alpha = self._slots(batch.frames)
        if self.identity is not None and batch.labels is not None:
            self._score_matching(alpha, batch.labels)
        slots = ordered.numpy().reshape(len(batch.frames), -1)
        self.batches_published += 1
        self.steps_published += len(batch)
        return TransitionBatch(worker_id=batch.worker_id, seq=batch.seq, policy_version=batch.policy_version,
                               state=slots[batch.state_frame], action=batch.action, reward=batch.reward,
                               next_state=slots[batch.next_frame], terminated=batch.terminated,
                               truncated=batch.truncated, episode_id=batch.episode_id, step=batch.step)

    def _score_matching(self, alpha: torch.Tensor, labels: np.ndarray) -> None:
        """Score the published order against the renderer's masks (slot ``m`` should hold segment ``m``)."""
        targets = mask_targets(alpha, torch.from_numpy(labels))
        scores = matching_accuracy(torch.arange(alpha.shape[1]).expand_as(targets), targets)
        frames = len(labels)
        self.live_matching += (scores["slot_accuracy"] * frames * alpha.shape[1], frames * alpha.shape[1],
                               scores["frame_accuracy"] * frames, frames)

    def matching(self) -> dict[str, float]:
        """The identity head's matching accuracy, held out when it was fitted (with the slots' FG-ARI on the same
        frames, no masks) and over every published frame with labels (``published_*``)."""
        out = {f"identity_{k}": v for k, v in self.identity_scores.items() if k.endswith("accuracy")}
        if "fg_ari" in self.identity_scores:
            out["fg_ari"] = self.identity_scores["fg_ari"]
        if self.live_matching[1]:
            out["published_identity_slot_accuracy"] = float(self.live_matching[0] / self.live_matching[1])
            out["published_identity_frame_accuracy"] = float(self.live_matching[2] / self.live_matching[3])
        return out

    def binding_warning(self) -> str | None:
        """Why the frozen slots should not be trusted, or None: a held-out FG-ARI below
        :data:`BOUND_FG_ARI` means slot attention froze before it bound the objects, and a graph over
        such slots is a graph over arbitrary image parts."""
        score = self.identity_scores.get("fg_ari")
        if score is None or score >= BOUND_FG_ARI:
            return None
        return (f"the slots froze unbound: held-out FG-ARI {score:.3f} < {BOUND_FG_ARI} after "
                f"{self.cfg.slot_updates} slot updates; a graph over them is not a graph over objects "
                f"(more --extractor-slot-updates, or another --seed)")

    def progress(self) -> dict[str, float]:
        updates = self.learner.updates if self.learner is not None else 0
        return {"slot_updates": updates, "frames_trained_on": self.frames_trained_on, "ready": float(self.ready),
                "batches_published": self.batches_published, "env_steps": self.steps_published,
                **{k: v for k, v in self.last_stats.items() if k != "phase"}, **self.matching()}

    def fingerprint(self) -> str:
        return json.dumps({"env": self.env.env_id, "env_config": json.loads(self.env.config_json),
                           "slots": dataclasses.asdict(self.slot_config), "ae_updates": self.cfg.ae_updates,
                           "slot_updates": self.cfg.slot_updates, "identity": self.cfg.identity}, sort_keys=True)

    def checkpoint(self, path: Path) -> None:
        """The slot model, its optimisers and phase, and the normalisation (frames are not kept: a restart
        before the slots froze refills its replay from new frames)."""
        if self.learner is None:
            return
        save_checkpoint({"fingerprint": self.fingerprint(), "frame_size": self.learner.frame_size,
                         "learner": self.learner.state_dict(), "locs": list(self.locs or ()),
                         "scales": list(self.scales or ()), "frames_trained_on": self.frames_trained_on,
                         "identity": self.identity.state_dict() if self.identity is not None else None,
                         "identity_scores": self.identity_scores}, path)

    def restore(self, path: Path) -> bool:
        saved = load_checkpoint(path)
        if saved is None:
            return False
        check_fingerprint(saved, self.fingerprint(), path)
        self._build(int(saved["frame_size"]))
        self.learner.load_state_dict(saved["learner"])
        if saved["scales"]:
            self.locs, self.scales = tuple(saved["locs"]), tuple(saved["scales"])
        self.frames_trained_on = int(saved["frames_trained_on"])
        if saved.get("identity") is not None:
            self.identity = SlotIdentity(self.slot_config.slot_dim, self.slot_config.num_slots)
            self.identity.load_state_dict(saved["identity"])
            self.identity_scores = dict(saved["identity_scores"])
        return True
