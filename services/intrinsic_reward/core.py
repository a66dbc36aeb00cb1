"""intrinsic-reward core: the newest weights of the run's method and its causal graph score transition
batches (or this service's own ensemble does). No bus."""
from __future__ import annotations

import numpy as np
import torch

from torch import nn

from causal.factored import FactorLayout
from causal.intrinsic import BootstrapEnsemble, make_reward, score
from causal.method import import_tensors
from causal.methods import get_method, model_from_config_json
from proto.codec import ProtocolError
from proto.fits import check_fits
from proto.messages import EnvSpec, GraphReport, ScoredBatch, TransitionBatch, Weights
from services.intrinsic_reward.config import IntrinsicRewardConfig
from services.runtime.accept import VersionGate, check_weights_config
from services.runtime.device import resolve_device


class IntrinsicRewardCore:
    """Scores batches with ``cfg.reward``. Until the first weights arrive every reward is 0 (with
    ``weights_version`` 0), so the policy-learner is never starved; until the first graph the
    causal parents are every input (PredDiff is then 0). A reward with a warm-up (its
    ``warmup_env_steps``) is 0 until the weights it reads have seen that many env steps.

    An ``ensemble`` reward reads this service's own :class:`BootstrapEnsemble`, trained on the
    batches after scoring them; its ``weights_version`` is the ensemble's update count."""

    def __init__(self, cfg: IntrinsicRewardConfig, spec: EnvSpec) -> None:
        self.cfg, self.spec = cfg, spec
        self.reward = make_reward(cfg.reward, cfg.eta)
        method = get_method(cfg.method)
        if self.reward.source == "dynamics" and cfg.reward not in method.intrinsic:
            raise ValueError(f"reward {cfg.reward!r} reads the dynamics model; method {method.name!r} serves "
                             f"{', '.join(method.intrinsic) or 'none'}")
        self.device = (resolve_device(cfg.device, method.devices) if self.reward.source == "dynamics"
                       else torch.device("cpu"))
        """Where the dynamics model scores batches (the ensemble of an ``ensemble`` reward stays on the CPU)."""
        self.model: nn.Module | None = None
        self.model_config = ""
        self.weights_version = 0
        self.weights_env_steps = 0
        self.graph_version = -1
        self.versions = VersionGate(known=cfg.known_version)
        """The learner's weights versions and the evaluator's report versions taken so far."""
        n = spec.num_factors
        self.parents = np.ones((n, n + 1), dtype=bool)
        self.ensemble = BootstrapEnsemble(FactorLayout.from_spec(spec), cfg.ensemble_members, cfg.ensemble_hidden,
                                          cfg.ensemble_lr, seed=cfg.seed) if self.reward.source == "ensemble" else None

    def load_weights(self, weights: Weights) -> bool:
        """Use newer weights. ValueError, before any model is built, for weights of another method or
        factor layout, whose configuration does not describe their tensors, or whose version jumps
        past the bound (:mod:`services.runtime.accept`)."""
        if weights.version <= self.weights_version or not self.versions.newer("weights", weights.version):
            return False
        if weights.config_json != self.model_config:
            check_weights_config(weights.config_json, weights.tensors, self.cfg.method, FactorLayout.from_spec(self.spec),
                                 model_from_config_json)
            self.model, self.model_config = model_from_config_json(weights.config_json).to(self.device), weights.config_json
        import_tensors(self.model, weights.tensors)
        self.versions.accept("weights", weights.version)
        self.weights_version, self.weights_env_steps = weights.version, weights.env_steps
        return True

    def apply_graph(self, report: GraphReport) -> bool:
        """Take PA(j) from the newest graph report; stale or misshapen reports are ignored, a version
        jump past the bound is refused (ProtocolError)."""
        if report.adjacency.shape != self.parents.shape:
            return False
        if report.weights_version < self.graph_version or (report.weights_version > self.graph_version
                                                            and not self.versions.newer("graph", report.weights_version)):
            return False
        self.versions.accept("graph", report.weights_version)
        self.graph_version = report.weights_version
        self.parents = report.adjacency.astype(bool)
        return True

    def score(self, batch: TransitionBatch) -> ScoredBatch:
        """The batch with its intrinsic rewards (ProtocolError if it does not fit the EnvSpec)."""
        check_fits(self.spec, batch)
        model = self.ensemble if self.ensemble is not None else self.model
        if self.ensemble is not None and self.ensemble.size < self.cfg.ensemble_warmup:
            model = None
        if model is not None and self.weights_env_steps < self.reward.warmup_env_steps(model):
            model = None
        if model is None:
            rewards = np.zeros(len(batch), np.float32)
        else:
            rewards = score(self.reward, model, self.parents, batch.state, batch.action, batch.next_state,
                            device=self.device if model is self.model else torch.device("cpu"))
        if not np.isfinite(rewards).all():
            raise ProtocolError("non_finite", f"intrinsic rewards of {batch.worker_id}/{batch.seq}")
        version = self.ensemble.updates if self.ensemble is not None else self.weights_version
        scored = ScoredBatch(transitions=batch, intrinsic_reward=rewards, reward_kind=self.reward.name,
                             weights_version=version)
        if self.ensemble is not None:
            self._train_ensemble(batch)
        return scored

    def _train_ensemble(self, batch: TransitionBatch) -> None:
        self.ensemble.add(batch.state, batch.action, batch.next_state)
        for _ in range(self.cfg.ensemble_updates_per_batch):
            self.ensemble.train_step(self.cfg.ensemble_batch_size)
