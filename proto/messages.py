"""Message schemas: every value that crosses a process boundary is one of these.

Each message is a frozen dataclass with a ``type`` tag and a ``schema_version``; arrays are numpy
arrays that travel as ``(dtype, shape, bytes)``. ``proto.codec`` encodes them with msgpack and
validates everything on decode. Field conventions:

* A *factored state* is a flat float32 vector: one slot per categorical factor (the category index)
  and ``size`` slots per continuous factor. ``EnvSpec.state_dim`` is its length.
* A *graph* is a ``d_S x (d_S + 1)`` matrix: row = factor at t+1, column = factor at t, the action
  in the last column.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

SCHEMA_VERSION = 10

FACTOR_KINDS = ("continuous", "categorical")
ACTION_KINDS = ("continuous", "categorical")
CONTROL_COMMANDS = ("pause", "resume", "checkpoint", "stop", "set_task", "scale")
SKILL_PHASES = ("pretrain", "task")
"""SkiLD's phases (ch. 6): reward-free skill pre-training, then task learning over the frozen skills."""
EDGE_RULES = ("fixed", "fdr")
"""How a graph report decides its edges: CMI >= threshold, or tests at a false-discovery rate."""
BIASES = ("fixed", "permuted", "pooled", "global", "split", "mirror", "mirror-permuted")
"""How the fdr rule allows for the learned model's bias: ``fixed`` tests ``CMI > min_cmi``;
``permuted`` tests ``CMI > null`` with the null estimated per entry from a permuted input; ``pooled``
tests ``CMI >`` the largest null of the entry's output, ``global`` the largest of the whole graph;
``split`` tests ``CMI >`` a minimum effect size cut from the CMI table's two clusters; ``mirror``
takes ``CMI >=`` the level where the entries below its negative count the non-edges above it at the
rate; ``mirror-permuted`` takes the same levels of ``CMI - null`` and of its z-score, and an entry
above both (``causal.edge_tests``)."""
NULL_BIASES = ("permuted", "pooled", "global", "mirror-permuted")
"""The biases that need the permuted-input null (``cmi_null``)."""


@dataclass(frozen=True)
class EnvSpec:
    """What an environment exposes: factor layout, action space and, where known, the true graph."""

    TYPE: ClassVar[str] = "EnvSpec"
    env_id: str
    factor_names: tuple[str, ...]
    factor_kinds: tuple[str, ...]
    factor_sizes: tuple[int, ...]
    """Categories of a categorical factor, dimensions of a continuous one."""
    factor_objects: tuple[str, ...]
    factor_locs: tuple[float, ...]
    """Normalisation hint per factor (0 for categorical): learners feed (x - loc) / scale."""
    factor_scales: tuple[float, ...]
    action_kind: str
    action_size: int
    """Number of discrete actions, or the dimension of a continuous action."""
    episode_length: int
    global_graph: np.ndarray | None = None
    """uint8 ``d_S x (d_S + 1)`` ground truth, or None when unknown."""
    config_json: str = "{}"
    """The environment's own configuration (graph, objects, seed), for reproducibility."""
    reward_parents: np.ndarray | None = None
    """uint8 ``[d_S + 1]``: which factors at t (and the action, last) the task's reward depends on,
    when known (schema version 4; chapter 4's causal reward model is scored against it)."""
    state_low: np.ndarray | None = None
    """float32 ``[state_dim]``: the env's declared observation space, lower bounds (an infinite bound
    travels as float32's largest value), when it declares one (schema version 6). Consumers refuse
    transitions outside ``[state_low, state_high]`` (``proto.codec.check_fits``)."""
    state_high: np.ndarray | None = None
    """float32 ``[state_dim]``: upper bounds, with ``state_low``."""

    @property
    def num_factors(self) -> int:
        return len(self.factor_names)

    @property
    def state_dim(self) -> int:
        return sum(1 if k == "categorical" else s for k, s in zip(self.factor_kinds, self.factor_sizes))

    @property
    def action_dim(self) -> int:
        return 1 if self.action_kind == "categorical" else self.action_size


WORKER_LIFE_EPISODES = 10**9
"""Episode ids of an env-worker's life k (after k restarts) start at k x this, so they stay unique per
worker id across restarts and tell its lives apart (each life counts ``seq`` from 0)."""


@dataclass(frozen=True)
class TransitionBatch:
    """A batch of consecutive steps from one env-worker (never single steps)."""

    TYPE: ClassVar[str] = "TransitionBatch"
    worker_id: str
    seq: int
    policy_version: int
    state: np.ndarray
    """float32 [T, state_dim]"""
    action: np.ndarray
    """float32 [T, action_dim] (a categorical action is its index in one column)"""
    reward: np.ndarray
    """float32 [T]"""
    next_state: np.ndarray
    """float32 [T, state_dim]"""
    terminated: np.ndarray
    """bool [T]"""
    truncated: np.ndarray
    """bool [T]"""
    episode_id: np.ndarray
    """int64 [T]; unique per worker; life k of a worker (its k-th restart) numbers its episodes from
    k x :data:`WORKER_LIFE_EPISODES`, and its ``seq`` from 0 again"""
    step: np.ndarray
    """int32 [T]; index of the step within its episode"""
    local_graph: np.ndarray | None = None
    """uint8 [T, d_S, d_S + 1] ground-truth local graphs, when the simulator can tell"""
    option: np.ndarray | None = None
    """int32 [T], when the collection policy acts over skills: the option (skill index) chosen at this
    step, -1 where the running skill goes on (schema version 2)"""

    def __len__(self) -> int:
        return int(self.state.shape[0])

    @property
    def life(self) -> int:
        """Which life of its worker sent this batch (0 for the first start, k after k restarts)."""
        return int(self.episode_id.min()) // WORKER_LIFE_EPISODES if len(self) else 0


@dataclass(frozen=True)
class FrameBatch:
    """A batch of consecutive steps from one env-worker as pixels, for the factor-extractor, which turns
    it into a TransitionBatch of slot factors (schema version 7; chapters 7-8).

    Consecutive steps share frames (step t's next observation is step t + 1's observation), so a frame
    travels once: ``frames`` holds the distinct frames and ``state_frame`` / ``next_frame`` index them.
    ``F`` is ``T + 1`` plus one per episode reset inside the batch, at most ``2T``."""

    TYPE: ClassVar[str] = "FrameBatch"
    worker_id: str
    seq: int
    policy_version: int
    frames: np.ndarray
    """uint8 [F, H, W, 3]"""
    state_frame: np.ndarray
    """int32 [T]: index in ``frames`` of each step's observation"""
    next_frame: np.ndarray
    """int32 [T]: index in ``frames`` of each step's next observation"""
    action: np.ndarray
    """float32 [T, action_dim] (as TransitionBatch)"""
    reward: np.ndarray
    """float32 [T]"""
    terminated: np.ndarray
    """bool [T]"""
    truncated: np.ndarray
    """bool [T]"""
    episode_id: np.ndarray
    """int64 [T]"""
    step: np.ndarray
    """int32 [T]"""
    labels: np.ndarray | None = None
    """uint8 [F, H, W]: each pixel's object (0: background, 1 + k: object k), when the renderer knows them
    (the exact masks that stand in for a segmentation model's, for the mask prior of eq. 7.1)"""

    def __len__(self) -> int:
        return int(self.state_frame.shape[0])


@dataclass(frozen=True)
class ScoredBatch:
    """Transitions plus the intrinsic reward computed for them by the intrinsic-reward service."""

    TYPE: ClassVar[str] = "ScoredBatch"
    transitions: TransitionBatch
    intrinsic_reward: np.ndarray
    """float32 [T]"""
    reward_kind: str
    weights_version: int


@dataclass(frozen=True)
class Weights:
    """A versioned model snapshot: named tensors plus the config needed to rebuild the module."""

    TYPE: ClassVar[str] = "Weights"
    model: str
    version: int
    config_json: str
    tensors: dict[str, np.ndarray] = field(default_factory=dict)
    updates: int = 0
    env_steps: int = 0


@dataclass(frozen=True)
class GraphReport:
    """A causal graph estimate with its CMI matrix, abstraction and scores against the truth."""

    TYPE: ClassVar[str] = "GraphReport"
    kind: str
    weights_version: int
    env_steps: int
    updates: int
    factor_names: tuple[str, ...]
    cmi: np.ndarray
    """float32 [d_S, d_S + 1], nats"""
    adjacency: np.ndarray
    """uint8 [d_S, d_S + 1]"""
    threshold: float
    controllable: tuple[int, ...]
    action_relevant: tuple[int, ...]
    action_irrelevant: tuple[int, ...]
    metrics: dict[str, float] = field(default_factory=dict)
    """accuracy, precision, recall, f1, roc_auc, best_threshold, best_threshold_f1 (when truth known)"""
    true_graph: np.ndarray | None = None
    num_heldout: int = 0
    timestamp: float = 0.0
    reward_scores: np.ndarray | None = None
    """float32 [d_S + 1]: a causal reward model's edge scores (CBM: reward CMI, nats), one per factor
    at t and the action last; only from a method with a reward graph (schema version 4)"""
    reward_parents: np.ndarray | None = None
    """uint8 [d_S + 1]: ``reward_scores >= reward_threshold``, the reward's learned parents"""
    reward_threshold: float = 0.0
    true_reward_parents: np.ndarray | None = None
    """uint8 [d_S + 1]: the env's true reward parents (``EnvSpec.reward_parents``), when known"""
    cmi_stderr: np.ndarray | None = None
    """float32 [d_S, d_S + 1], nats, >= 0: each entry's standard error, from the per-sample ratios
    behind its CMI; only from an estimator that has them (schema version 5)"""
    undecided: np.ndarray | None = None
    """uint8 [d_S, d_S + 1]: entries the data cannot yet decide (``causal.edge_tests.decide``); with
    ``cmi_stderr``"""
    edge_rule: str = "fixed"
    """``fixed``: edge if ``cmi >= threshold``; ``fdr``: edge if the test of ``cmi > min_cmi`` rejects
    at false-discovery rate ``fdr`` (Benjamini-Hochberg over the off-diagonal entries)"""
    fdr: float = 0.0
    min_cmi: float = 0.0
    """The minimum effect size tested against: the configured one, or under ``bias`` split, mirror or
    mirror-permuted the level cut from this report's CMI (of ``cmi - cmi_null`` under mirror-permuted;
    the configured one where that rule found none)"""
    bias: str = "fixed"
    """How the fdr rule allowed for the estimator's bias (:data:`BIASES`; schema version 8): ``fixed``,
    the test of ``cmi > min_cmi``; ``split``, the same with ``min_cmi`` estimated; ``mirror``, ``cmi >=``
    the level ``min_cmi`` estimated from the table's negative side; ``mirror-permuted``, ``cmi - cmi_null
    >=`` its level ``min_cmi`` (and its z-score above its own level); otherwise of ``cmi`` above the
    permuted-input null"""
    cmi_null: np.ndarray | None = None
    """float32 [d_S, d_S + 1], nats: each entry's CMI with its input permuted across the held-out
    samples (the estimated bias of a non-edge); with a ``bias`` of :data:`NULL_BIASES`"""
    reward_stderr: np.ndarray | None = None
    """float32 [d_S + 1], >= 0: the reward scores' standard errors (CBM: delta method), when known"""
    reward_undecided: np.ndarray | None = None
    """uint8 [d_S + 1]: reward entries the data cannot yet decide, with ``reward_stderr``"""
    reward_min_cmi: float = 0.0
    """The minimum effect size the fdr rule tested the reward scores against (the configured
    ``min_cmi``: the reward row has no null and no estimated level, so under ``bias`` split or mirror
    it differs from ``min_cmi``, the dynamics level); 0 unless the reward was tested (schema version 9)"""

    def decided_graph(self) -> bytes:
        """The graph as decided (adjacency and, with a reward graph, the reward's parents), as bytes to
        compare reports by: the stop rule's and the evaluator's "same graph"."""
        return self.adjacency.tobytes() + (b"" if self.reward_parents is None else self.reward_parents.tobytes())

    def undecided_count(self) -> int | None:
        """Undecided entries of both graphs (None without standard errors: nothing can be undecided)."""
        if self.undecided is None:
            return None
        return int(self.undecided.sum()) + (0 if self.reward_undecided is None else int(self.reward_undecided.sum()))


@dataclass(frozen=True)
class LocalGraphReport:
    """Local (per-transition) dependency graphs a method estimated for a sample of held-out
    transitions, scored against the simulator's true local graphs (schema version 3).

    ``metrics`` pool every off-diagonal entry of every sampled transition: ``roc_auc``, ``pr_auc``
    (average precision), ``best_f1`` at ``best_threshold``, ``f1`` / ``precision`` / ``recall`` at
    ``threshold``, ``positive_rate`` (share of true edges). ``scores`` and ``truth`` carry a few of
    the sampled transitions for display."""

    TYPE: ClassVar[str] = "LocalGraphReport"
    kind: str
    """The method (``graph/<kind>`` names its global graph)."""
    estimator: str
    """What the scores are (``pcmi``: point-wise CMI in nats; ELDEN: gradient magnitudes)."""
    weights_version: int
    env_steps: int
    updates: int
    factor_names: tuple[str, ...]
    threshold: float
    scores: np.ndarray
    """float32 [K, d_S, d_S + 1]: edge scores of K example transitions"""
    truth: np.ndarray
    """uint8 [K, d_S, d_S + 1]: their true local graphs"""
    metrics: dict[str, float] = field(default_factory=dict)
    num_transitions: int = 0
    """Transitions the metrics pool."""
    timestamp: float = 0.0


@dataclass(frozen=True)
class SkillBatch:
    """Transitions collected by SkiLD's skill policy, with the skill each step ran (schema version 7).

    A skill is ``z = (G, b)``: ``slot`` indexes the learner's graph history's targets (append-only,
    so a slot names the same target graph in every later policy version; -1: no target yet), ``b``
    is the diversity index. ``started`` marks the steps where a new skill was picked (by the graph
    selector in ``pretrain``, by the task policy in ``task``, whose option is ``slot * K + b``)."""

    TYPE: ClassVar[str] = "SkillBatch"
    transitions: TransitionBatch
    phase: str
    """One of ``SKILL_PHASES``: the phase of the policy that collected the batch."""
    slot: np.ndarray
    """int32 [T]: the running skill's target slot, -1 while the history has no target"""
    b: np.ndarray
    """int32 [T]: the running skill's diversity index"""
    started: np.ndarray
    """bool [T]: a skill was picked at this step"""


@dataclass(frozen=True)
class InducedGraphs:
    """The local graphs a method's estimator induced for every step of one TransitionBatch (schema
    version 7): the graph-evaluator's answer to SkiLD's question "which dependencies did this step
    induce?" (pCMI >= the method's threshold, self-edges always, an unchanged factor only its own)."""

    TYPE: ClassVar[str] = "InducedGraphs"
    kind: str
    """The method whose model scored them."""
    worker_id: str
    seq: int
    """The TransitionBatch ``(worker_id, seq)`` the graphs belong to."""
    weights_version: int
    graphs: np.ndarray
    """uint8 [T, d_S, d_S + 1]"""


@dataclass(frozen=True)
class LatentActions:
    """FLAM's per-slot latent actions of every step of one env-worker FrameBatch (schema version 10; ch. 8):
    the factor-extractor's labels of the workers' stream, from the learner's FLAM weights, one
    Gaussian posterior (eq. 8.4) per step and slot, inferred from the clip (s_t, s_{t+1})."""

    TYPE: ClassVar[str] = "LatentActions"
    kind: str
    """The method whose model labelled the steps."""
    worker_id: str
    seq: int
    """The FrameBatch ``(worker_id, seq)`` the labels belong to."""
    weights_version: int
    episode_id: np.ndarray
    """int64 [T]: the steps' episodes (as the batch's)"""
    step: np.ndarray
    """int32 [T]: the steps' indices in their episodes"""
    mean: np.ndarray
    """float32 [T, K, d_a]: each slot's posterior mean"""
    log_sigma: np.ndarray
    """float32 [T, K, d_a]: each slot's posterior log standard deviation"""

    def __len__(self) -> int:
        return int(self.mean.shape[0])


@dataclass(frozen=True)
class Control:
    """An operator command for one service (or ``*``)."""

    TYPE: ClassVar[str] = "Control"
    command: str
    argument: str = ""
    issued_at: float = 0.0


@dataclass(frozen=True)
class ServiceStats:
    """A periodic progress beat from one service instance, for the supervisor's live display."""

    TYPE: ClassVar[str] = "ServiceStats"
    service: str
    instance: str
    values: dict[str, float] = field(default_factory=dict)
    timestamp: float = 0.0


MESSAGE_TYPES: dict[str, type] = {
    cls.TYPE: cls
    for cls in (EnvSpec, TransitionBatch, FrameBatch, ScoredBatch, Weights, GraphReport, LocalGraphReport, Control, ServiceStats)
}
MESSAGE_TYPES.update({cls.TYPE: cls for cls in (SkillBatch, InducedGraphs)})  # SkiLD (ch. 6)
MESSAGE_TYPES[LatentActions.TYPE] = LatentActions  # FLAM (ch. 8)
