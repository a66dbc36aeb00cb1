"""dynamics-learner core: replay + the method's trainer + weight export + checkpoints. No bus; no
particular method (the run's comes from the registry)."""
from __future__ import annotations

import json
from pathlib import Path

import torch

from causal.factored import FactorLayout
from causal.method import ClipTrainer, PrioritisedTrainer, export_tensors
from causal.methods import get_method, method_config
from causal.replay import PrioritisedReplay, ReplayBuffer, heldout_mask
from proto.fits import check_fits
from proto.messages import EnvSpec, GraphReport, TransitionBatch, Weights
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.gaps import SeqGaps
from services.runtime.accept import VersionGate
from services.runtime.checkpoint import check_fingerprint, load_checkpoint, save_checkpoint
from services.runtime.device import resolve_device

class DynamicsLearnerCore:
    """Consumes training transitions, trains the method's dynamics model (CDL: eq. 3.3), and gives
    the trainer the newest global graph (CDL: the parents of the causal term)."""

    def __init__(self, cfg: DynamicsLearnerConfig, spec: EnvSpec) -> None:
        self.cfg, self.spec = cfg, spec
        self.method = get_method(cfg.method)
        self.layout = FactorLayout.from_spec(spec)
        self.trainer = self.method.trainer(self.layout, method_config(cfg.models, cfg.method), cfg.seed)
        self.device = resolve_device(cfg.device, self.method.devices)
        if "cuda" in self.method.devices:  # a method that runs on the CPU only has no ``to``
            self.trainer.to(self.device)
        self.clip_frames = self.trainer.clip_frames if isinstance(self.trainer, ClipTrainer) else 2
        """States per training clip: above 2, ``update_clips`` on clips cut from the replay (FLAM)."""
        self.reports_priorities = isinstance(self.trainer, PrioritisedTrainer)
        replay = PrioritisedReplay if self.method.prioritised else ReplayBuffer
        self.replay = replay(cfg.replay_capacity, spec.state_dim, spec.action_dim, seed=cfg.seed)
        self.version = 0
        self.env_steps = 0
        self.graph_version = -1
        self.graph_versions = VersionGate()
        """The evaluator's report versions taken so far: each must move forward by a bounded step."""
        self.last_stats: dict[str, float] = {}
        self.resumed_at_update = 0
        self.resumed_env_steps = 0
        """Env steps the checkpoint held when this process resumed (what a restart kept of the data)."""
        self.gaps = SeqGaps()
        """Batches lost on the way here (``seq`` gaps per worker life); checkpointed with the replay, so
        what a restart loses (taken after the checkpoint, or sent while down) counts as lost too."""

    def ingest(self, batch: TransitionBatch) -> int:
        """Keep the training episodes of ``batch``; returns how many steps were kept.

        Raises ProtocolError('inconsistent') for a batch that does not fit the EnvSpec (nothing kept).
        A batch already taken (same worker, life and ``seq``) is not kept again."""
        check_fits(self.spec, batch)
        if self.gaps.observe(batch.worker_id, batch.life, batch.seq, len(batch)) == "duplicate":
            return 0
        self.env_steps += len(batch)
        keep = ~heldout_mask(batch.worker_id, batch.episode_id, self.cfg.heldout_fraction)
        self.replay.add(batch.state[keep], batch.action[keep], batch.next_state[keep], batch.reward[keep])
        return int(keep.sum())

    @property
    def ready(self) -> bool:
        return self.replay.size >= max(self.cfg.warmup_steps, self.trainer.batch_size)

    @property
    def may_update(self) -> bool:
        """Ready, and below ``updates_per_env_step`` x env steps ingested when that ratio is set.

        Both counts are checkpointed, so a resumed learner keeps the ratio."""
        ratio = self.cfg.updates_per_env_step
        return self.ready and (ratio <= 0 or self.trainer.updates < ratio * self.env_steps)

    def train_step(self) -> dict[str, float]:
        """One update on a replay batch. For a ``prioritised`` method the batch is drawn by priority
        and the rows get the priorities a :class:`~causal.method.PrioritisedTrainer` reports for them
        (``None`` to leave them: every row then keeps its first priority, and sampling is uniform).
        A :class:`~causal.method.ClipTrainer` whose ``clip_frames`` is above 2 is given clips of that
        many consecutive states instead (:meth:`causal.replay.ReplayBuffer.sample_clips`; FLAM)."""
        if self.clip_frames > 2:
            clips = self.replay.sample_clips(self.trainer.batch_size, self.clip_frames)
            stats = self.trainer.update_clips(*self._on_device((clips,)))
        elif not isinstance(self.replay, PrioritisedReplay):
            stats = self.trainer.update(*self._on_device(self.replay.sample(self.trainer.batch_size,
                                                                            self.method.learns_reward)))
        else:
            index, batch = self.replay.sample_indexed(self.trainer.batch_size, self.method.learns_reward)
            stats = self.trainer.update(*self._on_device(batch))
            if self.reports_priorities and self.trainer.last_priorities is not None:
                self.replay.update_priorities(index, self.trainer.last_priorities)
        self.last_stats.update(stats)
        return stats

    def _on_device(self, batch: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
        return batch if self.device.type == "cpu" else tuple(t.to(self.device) for t in batch)

    def apply_graph(self, report: GraphReport) -> bool:
        """Give the trainer the evaluator's graph (CDL: PA(S^j) for the causal term); stale, misshapen
        and other methods' reports are ignored, a version jump past the bound is refused (ProtocolError)."""
        n = self.spec.num_factors
        if (report.kind != self.method.name or report.weights_version < self.graph_version
                or report.adjacency.shape != (n, n + 1)
                or not self.graph_versions.take("graph", report.weights_version, ceiling=self.version)):
            return False
        self.graph_version = report.weights_version
        self.trainer.set_parents(report.adjacency)
        return True

    def weights(self) -> Weights:
        """The next version of the weights. A caller that publishes it records it first with
        :meth:`record_version`, so a restarted learner never publishes a version twice."""
        self.version += 1
        return Weights(model=self.method.name, version=self.version, config_json=self.trainer.config_json(),
                       tensors=export_tensors(self.trainer.model), updates=self.trainer.updates,
                       env_steps=self.env_steps)

    def fingerprint(self) -> str:
        """What a checkpoint must match to be resumed: the environment and the model's configuration.

        The method's resumable settings are left out (``Method.resumable``; CDL: the learning-rate
        schedule): a run may be resumed with another one (say, to decay a run trained at a constant
        rate), and checkpoints written before the schedule existed still match."""
        model = self.method.fingerprint(self.trainer.config_json())
        return json.dumps({"env": self.spec.env_id, "env_config": json.loads(self.spec.config_json),
                           "model": model}, sort_keys=True)

    def checkpoint(self, path: Path) -> None:
        save_checkpoint({"fingerprint": self.fingerprint(), "model_config": self.trainer.config_json(),
                         "trainer": self.trainer.state_dict(),
                         "replay": self.replay.state_dict(),
                         "version": self.version, "env_steps": self.env_steps,
                         "graph_version": self.graph_version, "seq_gaps": self.gaps.state_dict()}, path)

    @staticmethod
    def version_path(checkpoint: Path) -> Path:
        """The high-water mark of published versions, beside the checkpoint (a small JSON file)."""
        return checkpoint.with_suffix(".version.json")

    def record_version(self, checkpoint: Path) -> None:
        """Record ``self.version`` as published (atomically), before it is published.

        The checkpoint is written every ``checkpoint_every_s`` and weights every ``publish_every_s``,
        so a learner killed between two checkpoints has published versions its checkpoint does not
        know; consumers ignore versions they have seen, and a resumed learner that counted from the
        checkpoint's version was ignored until it passed them (issue 20). One tiny file per publish."""
        path = self.version_path(checkpoint)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"version": self.version}))
        tmp.replace(path)

    def _published_version(self, checkpoint: Path) -> int:
        try:
            return int(json.loads(self.version_path(checkpoint).read_text())["version"])
        except (OSError, ValueError, KeyError, TypeError):
            return 0

    def restore(self, path: Path) -> bool:
        """Resume from the checkpoint at ``path``; versions continue above any published before,
        whether or not a checkpoint exists (a learner restarted without one starts a new model, and
        its weights must still be newer than what consumers hold)."""
        self.version = max(self.version, self._published_version(path))
        saved = load_checkpoint(path)
        if saved is None:
            return False
        check_fingerprint(saved, self.fingerprint(), path)
        self.trainer.load_state_dict(saved["trainer"])
        self.replay.load_state_dict(saved["replay"])
        self.version = max(int(saved["version"]), self._published_version(path))
        self.env_steps = int(saved["env_steps"])
        self.graph_version = int(saved["graph_version"])
        if "seq_gaps" in saved:  # checkpoints written before the loss was counted have none
            self.gaps.load_state_dict(saved["seq_gaps"])
        self.resumed_at_update, self.resumed_env_steps = self.trainer.updates, self.env_steps
        return True

    def progress(self) -> dict[str, float]:
        return {"updates": self.trainer.updates, "env_steps": self.env_steps, "replay_size": self.replay.size,
                "weights_version": self.version, "resumed_at_update": self.resumed_at_update,
                "resumed_env_steps": self.resumed_env_steps,
                "lr": self.trainer.lr, **self.gaps.stats(), **self.last_stats}
