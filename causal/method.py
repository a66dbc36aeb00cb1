"""What a causal method is made of: small role interfaces and the registry entry that bundles them.

The services are generic: the dynamics-learner trains whatever :attr:`Method.trainer` builds, the
graph-evaluator runs the method's :attr:`Method.global_graph` (and :attr:`Method.local_graph`)
estimators on the published weights, the policy-learner masks its input with the graph report's
abstraction (:attr:`Method.abstraction`), the intrinsic-reward service serves the rewards the model
supports (:attr:`Method.intrinsic`). A method adds a module under ``causal/methods/`` that builds one
:class:`Method` and one line in :data:`causal.methods.METHODS`; no service changes. A role a method
does not have is ``None`` (a method without a global graph publishes no graph reports).

Graphs are ``d_S x (d_S + 1)`` (row = factor at t+1, column = factor at t, the action last), as
everywhere in Causeway; edge scores are "higher = more of an edge" and compared with a threshold.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Mapping, Protocol, runtime_checkable

import numpy as np
import torch
from torch import nn

from causal.abstraction import Abstraction, cdl_abstraction
from causal.edge_tests import EdgeEstimate
from causal.factored import FactorLayout
from proto.messages import EnvSpec


class DynamicsTrainer(Protocol):
    """A dynamics model and everything that trains it; the dynamics-learner's core drives one."""

    model: nn.Module
    updates: int
    batch_size: int
    """Transitions per update (the learner samples batches of this size from its replay)."""

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        """One training step on a batch; returns its losses (``nll_*`` keys: nats per factor). A method
        that ``learns_reward`` is called with the batch's rewards as a fourth argument."""

    def set_parents(self, adjacency: np.ndarray) -> None:
        """Graph feedback: the newest global graph (only called when the method has one)."""

    @property
    def lr(self) -> float:
        """Learning rate of the next update."""

    def config_json(self) -> str:
        """Everything needed to rebuild :attr:`model` from its exported tensors (``{"model": name, ...}``)."""

    def state_dict(self) -> dict[str, Any]:
        """Checkpoint state; ``"model"`` holds the model's ``state_dict``."""

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


@runtime_checkable
class ClipTrainer(Protocol):
    """Optional part of a :class:`DynamicsTrainer` that learns from clips of consecutive states (FLAM):
    with ``clip_frames`` above 2 the learner calls ``update_clips`` instead of ``update``."""

    clip_frames: int
    """States per clip (2: the learner keeps calling ``update`` on transitions)."""

    def update_clips(self, states: torch.Tensor) -> dict[str, float]:
        """One training step on ``[batch, clip_frames, state_dim]`` consecutive states."""


@runtime_checkable
class PrioritisedTrainer(Protocol):
    """Optional part of a :class:`DynamicsTrainer` of a ``prioritised`` method (ELDEN): after each
    ``update`` the new priorities of the batch's rows, ``None`` to leave them."""

    last_priorities: np.ndarray | None


class GlobalGraphEstimator(Protocol):
    """Per-edge scores of the whole environment's graph from a model and held-out transitions."""

    name: str
    """What the scores are (``cmi``: nats), shown on the page and in the summary."""

    def scores(self, model: nn.Module, state: torch.Tensor, action: torch.Tensor,
               next_state: torch.Tensor) -> np.ndarray:
        """``[d_S, d_S + 1]`` float scores over these transitions."""

    def threshold(self, model: nn.Module) -> float:
        """Edge if score >= this (from the model's own configuration)."""


@runtime_checkable
class EdgeEstimator(Protocol):
    """A global-graph estimator whose scores are means of per-sample terms (CDL's CMI: log-likelihood
    ratios) can give each entry a standard error too; the evaluator then reports them, the undecided
    entries, and can decide edges by tests at a false-discovery rate (:mod:`causal.edge_tests`)."""

    def estimate(self, model: nn.Module, state: torch.Tensor, action: torch.Tensor,
                 next_state: torch.Tensor, permute: torch.Generator | None = None) -> EdgeEstimate:
        """The scores of :meth:`GlobalGraphEstimator.scores` with their standard errors; with
        ``permute``, also the permuted-input null (:mod:`causal.edge_tests`; ValueError from an
        estimator that cannot compute one)."""


@runtime_checkable
class RewardEdgeEstimator(Protocol):
    """A reward-graph estimator that gives each entry a standard error too (CBM's reward CMI)."""

    def estimate(self, model: nn.Module, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                 reward: torch.Tensor) -> EdgeEstimate:
        """The scores of :meth:`RewardGraphEstimator.scores` ``[d_S + 1]`` with their standard errors."""


def has_standard_errors(method: "Method") -> bool:
    """Whether ``method``'s global graph comes with standard errors (:class:`EdgeEstimator`)."""
    return isinstance(method.global_graph, EdgeEstimator)


def permuted_null_refusal(method: "Method", cfg: Any) -> str | None:
    """Why ``method`` with its settings ``cfg`` has no permuted-input null (the evaluator's ``bias``
    other than fixed), or None when it has one. Without standard errors there is none; an estimator
    whose null depends on the settings says so with a ``permuted_null_refusal(cfg)`` method."""
    if not has_standard_errors(method):
        return f"method {method.name!r} has no standard errors, so no permuted-input null"
    check = getattr(method.global_graph, "permuted_null_refusal", None)
    return check(cfg) if check is not None else None


class LocalGraphEstimator(Protocol):
    """Per-transition edge scores: the local dependency graph of each transition (chapters 5-6)."""

    name: str

    def scores(self, model: nn.Module, state: torch.Tensor, action: torch.Tensor,
               next_state: torch.Tensor) -> np.ndarray:
        """``[B, d_S, d_S + 1]`` float scores, one graph per transition."""

    def threshold(self, model: nn.Module) -> float: ...


class RewardGraphEstimator(Protocol):
    """Which factors (and the action) the reward depends on (chapter 4's causal reward model)."""

    name: str

    def scores(self, model: nn.Module, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
               reward: torch.Tensor) -> np.ndarray:
        """``[d_S + 1]`` float scores: one per state factor, the action last."""

    def threshold(self, model: nn.Module) -> float: ...


class SlotScorer(Protocol):
    """Scores of a method's object slots (chapter 7's representation): the run summary's ``slots`` block."""

    def scores(self, model: nn.Module, spec: EnvSpec) -> dict[str, Any]:
        """``{"fg_ari": ..., ...}`` of the final ``model`` on frames of the run's environment ``spec``."""


class LatentActionScorer(Protocol):
    """Scores of a method's latent actions (chapter 8's FLAM): the run summary's ``latent_actions`` block."""

    def scores(self, model: nn.Module, spec: EnvSpec) -> dict[str, Any]:
        """``{"psnr": ..., "dci_d": ..., "dci_c": ..., "dci_i": ..., ...}`` of the final ``model`` on unseen
        videos of the run's environment ``spec``."""


TaskAbstraction = Callable[[np.ndarray], Abstraction]
"""A global graph (with self-edges) -> which factors a policy sees (``Abstraction.kept``)."""

RewardTaskAbstraction = Callable[[np.ndarray, "np.ndarray | None"], Abstraction]
"""A task abstraction that also reads the reward's parents (``[d_S + 1]`` 0/1, action last; None when
unknown): chapter 4's minimal abstraction. A method with a :attr:`Method.reward_graph` registers one as
its ``abstraction``; :func:`task_abstraction` passes it the learned reward parents."""

RolloutStep = Callable[..., Callable[[torch.Tensor, torch.Tensor], torch.Tensor]]
"""``(model, parents [d_S, d_S + 1] bool, factors=None) -> step(state, action) -> next state``: the
model used as a simulator (k-step prediction, planning), where the method's model can be one."""


@dataclass(frozen=True)
class Method:
    """A registered causal method: its settings, its model, and the roles it fills."""

    name: str
    title: str
    """One line for humans: what the method is, and the chapter."""
    config: type
    """Frozen dataclass of the method's hyper-parameters; ``causeway run`` offers its fields as
    ``--<name>-<field>`` flags (``proto.settings.doc`` gives each its help)."""
    trainer: Callable[[FactorLayout, Any, int], DynamicsTrainer]
    """``(layout, config, seed) -> trainer``."""
    model_from_config: Callable[[dict[str, Any]], nn.Module]
    """The parsed :meth:`DynamicsTrainer.config_json` -> an untrained model of the same shape."""
    global_graph: GlobalGraphEstimator | None = None
    local_graph: LocalGraphEstimator | None = None
    reward_graph: RewardGraphEstimator | None = None
    abstraction: TaskAbstraction = cdl_abstraction
    intrinsic: tuple[str, ...] = ()
    """Intrinsic rewards (``causal.intrinsic.REWARDS``) that read this method's model."""
    rollout_step: RolloutStep | None = None
    slots: SlotScorer | None = None
    """Object slots learned from frames (Dyn-O): the summary's ``slots`` block, from the final model."""
    latent_actions: LatentActionScorer | None = None
    """Per-slot latent actions learned from video (FLAM): the summary's ``latent_actions`` block, from the final model."""
    envs: tuple[str, ...] = ()
    """Environments the method runs on (empty: any); ``causeway run`` refuses others before starting."""
    env_settings: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    """Env name -> settings of :attr:`config` that env implies (``causeway run`` sets them, whatever the
    flags say): Dyn-O draws its own frames, so on ``chemical-pixels-two-tone`` it draws two-part objects."""
    check_layout: Callable[[FactorLayout, Any], None] | None = None
    """``(layout, config)``: raises ``ValueError`` for settings the env's factors cannot take (``causeway
    run`` calls it before starting, so a learner never fails on them mid-run)."""
    resumable: tuple[str, ...] = ()
    """Config fields a resumed learner may change (left out of the checkpoint fingerprint)."""
    prioritised: bool = False
    """The learner samples its replay in proportion to priorities the trainer reports for the rows it
    was given (prediction-error prioritisation, chapter 5), instead of uniformly."""
    learns_reward: bool = False
    """The trainer's ``update`` also takes the batch's rewards (a causal reward model, chapter 4):
    ``update(state, action, next_state, reward)``."""
    devices: tuple[str, ...] = ("cpu",)
    """Torch device types its trainer and estimators run on (``--device``). A method listing ``cuda``
    keeps every tensor it makes on its inputs' device, its trainer has ``to(device)`` (the model and the
    trainer's own tensors; batches arrive on that device) and its estimators return CPU arrays."""

    def config_json(self, layout: FactorLayout, cfg: Any) -> str:
        return model_config_json(self.name, layout, cfg)

    def fingerprint(self, config_json: str) -> dict[str, Any]:
        """The model configuration without the :attr:`resumable` fields (what a checkpoint must match)."""
        model = json.loads(config_json)
        for key in self.resumable:
            model.get(self.name, {}).pop(key, None)
        return model


def task_abstraction(method: Method, adjacency: np.ndarray, reward_parents: np.ndarray | None = None) -> Abstraction:
    """The method's abstraction of ``adjacency``: with the reward's parents for a method that has a reward
    graph (:data:`RewardTaskAbstraction`), from the graph alone otherwise (:data:`TaskAbstraction`)."""
    if method.reward_graph is not None:
        return method.abstraction(adjacency, reward_parents)
    return method.abstraction(adjacency)


def model_config_json(method: str, layout: FactorLayout, cfg: Any) -> str:
    """The model configuration every method publishes: its name, the factor layout, its settings."""
    return json.dumps({"model": method, "layout": asdict(layout), method: asdict(cfg)}, sort_keys=True)


def layout_from_config(data: dict[str, Any]) -> FactorLayout:
    """The factor layout stored in a model configuration by :meth:`Method.config_json`."""
    return FactorLayout(**{k: tuple(v) if isinstance(v, list) else v for k, v in data["layout"].items()})


def export_tensors(model: nn.Module) -> dict[str, np.ndarray]:
    """Parameters as numpy arrays for a ``Weights`` message (buffers are rebuilt from the config)."""
    return {name: p.detach().cpu().numpy().copy() for name, p in model.named_parameters()}


def import_tensors(model: nn.Module, tensors: dict[str, np.ndarray]) -> None:
    """Load parameters published by ``export_tensors``; names and shapes must match exactly."""
    params = dict(model.named_parameters())
    if set(params) != set(tensors):
        raise ValueError(f"parameter names differ: missing {sorted(set(params) - set(tensors))[:3]}, "
                         f"unexpected {sorted(set(tensors) - set(params))[:3]}")
    with torch.no_grad():
        for name, value in tensors.items():
            if tuple(value.shape) != tuple(params[name].shape):
                raise ValueError(f"{name}: shape {value.shape} != {tuple(params[name].shape)}")
            params[name].copy_(torch.from_numpy(np.ascontiguousarray(value, dtype=np.float32)))
