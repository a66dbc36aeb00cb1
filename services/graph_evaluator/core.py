"""graph-evaluator core: held-out set, the method's edge scores (CDL: CMI, with standard errors) with a
moving average, graph (fixed threshold or FDR tests), reward graph (CBM), abstraction, scores. No bus;
no particular method (the run's comes from the registry)."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from torch import nn

from causal.abstraction import with_self_edges
from causal.edge_tests import EdgeEstimate, decide, effect_level
from causal.factored import FactorLayout
from causal.graph_metrics import score_graph
from causal.method import EdgeEstimator, RewardEdgeEstimator, has_standard_errors, import_tensors, task_abstraction
from causal.methods import get_method, model_from_config_json
from causal.replay import ReplayBuffer, heldout_mask
from envs.registry import ENVS
from proto.fits import check_fits
from causal.skild import induced_local_graphs
from proto.messages import NULL_BIASES, EnvSpec, GraphReport, InducedGraphs, LocalGraphReport, TransitionBatch, Weights
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.local import LocalGraphScorer
from services.graph_evaluator.reward import abstraction_metrics, reward_metrics
from services.runtime.accept import VersionGate, check_weights_config
from services.runtime.checkpoint import check_fingerprint, load_checkpoint, save_checkpoint
from services.runtime.device import resolve_device

def constant_factor_indices(spec: EnvSpec) -> tuple[int, ...]:
    """Indices of the spec's factors that never vary (its registry entry's ``constant_factors``; an env
    not in the registry has none): their columns are left out of the identifiable scores."""
    entry = ENVS.get(spec.env_id)
    return tuple(spec.factor_names.index(name) for name in (entry.constant_factors if entry else ()))


class EvaluationDraw:
    """How many held-out transitions each evaluation draws (issue 22, item 3: more data where it decides).

    It starts at ``base``. When the graph has stayed the same for ``reports`` reports in a row while
    some entry is still undecided (its interval straddles the rule's boundary), the draw doubles, up to
    ``most``, and the count starts again at the new size. A stable graph with undecided entries is a
    graph the learner has settled but the evaluation's sampling error has not: a weak edge's standard
    error falls as 1 / sqrt(draw), so more data is what decides it. The draw never shrinks: once the
    graph needed it, a smaller one would bring the undecided entries back and undo the stop rule's
    count. A graph that keeps changing does not grow the draw (the model, not the data, moves it)."""

    def __init__(self, base: int, most: int, reports: int) -> None:
        self.base, self.most, self.reports = base, max(base, most), reports
        self.size = base
        self.count = 0
        self._graph = b""

    def observe(self, graph: bytes, undecided: int) -> bool:
        """Count one report (its graph's bytes, its undecided entries); whether the draw grew."""
        if graph == self._graph:
            self.count += 1
        else:
            self._graph, self.count = graph, 1
        if undecided and self.count >= self.reports and self.size < self.most:
            self.size, self.count = min(2 * self.size, self.most), 0
            return True
        return False

    def state_dict(self) -> dict[str, int]:
        return {"size": self.size}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.size = min(max(int(state["size"]), self.base), self.most)


class GraphEvaluatorCore:
    """Turns dynamics weights into GraphReports scored against the EnvSpec's ground truth, with the
    global-graph estimator of the run's method (``cfg.method``)."""

    def __init__(self, cfg: GraphEvaluatorConfig, spec: EnvSpec) -> None:
        self.cfg, self.spec = cfg, spec
        self.method = get_method(cfg.method)
        if cfg.edge_rule == "fdr" and not has_standard_errors(self.method):
            raise ValueError(f"edge_rule fdr needs standard errors of the graph's scores; {cfg.method}'s have none")
        if cfg.bias != "fixed" and not has_standard_errors(self.method):
            raise ValueError(f"bias {cfg.bias} needs standard errors (and, but for split and mirror, the permuted-input null) "
                             f"of the graph's scores; {cfg.method}'s have none")
        self.permute = torch.Generator().manual_seed(cfg.seed + 2) if cfg.bias in NULL_BIASES else None
        """Draws the permutation of each estimate's permuted-input null (``bias`` permuted or pooled)."""
        self.kind = self.method.name
        self.device = resolve_device(cfg.device, self.method.devices)
        self.constant_factors = constant_factor_indices(spec)
        self.heldout = ReplayBuffer(cfg.heldout_capacity, spec.state_dim, spec.action_dim, seed=cfg.seed)
        self.local = (LocalGraphScorer(spec, self.method.local_graph, self.kind, cfg.local_capacity, cfg.local_samples,
                                       cfg.local_examples, cfg.seed + 1, self.device)
                      if self.method.local_graph is not None else None)
        """Local-graph scoring, for a method with a local-graph estimator (fed by batches with true local graphs)."""
        self.model: nn.Module | None = None
        self.model_config = ""
        self.weights: Weights | None = None
        self.layout = FactorLayout.from_spec(spec)
        self.versions = VersionGate(known=cfg.known_version)
        """The learner's versions taken so far: each must move forward by a bounded step, the first from
        the version known published (the supervisor's, or this evaluator's checkpoint's)."""
        self.evaluated_version = -1
        self.evaluated_updates = 0
        self.cmi_ema: np.ndarray | None = None
        self.stderr_ema: np.ndarray | None = None
        """Standard errors of ``cmi_ema`` (averaged alike: an upper bound, see :meth:`evaluate`), for an
        estimator that has them."""
        self.null_ema: np.ndarray | None = None
        self.excess_stderr_ema: np.ndarray | None = None
        """The permuted-input null and the standard error of ``cmi - null``, averaged alike (``bias`` not fixed)."""
        self.threshold = float("nan")
        """Edge threshold of the loaded model's global-graph estimator (its own configuration)."""
        self.reward_ema: np.ndarray | None = None
        """Moving average of the reward graph's scores ``[d_S + 1]``, for a method with a reward graph."""
        self.reward_threshold = float("nan")
        self.reward_stderr_ema: np.ndarray | None = None
        """Standard errors of ``reward_ema`` (a reward estimator that has them: CBM's)."""
        self.history: list[dict[str, float]] = []
        self.draw = EvaluationDraw(cfg.eval_samples, cfg.eval_samples_max if has_standard_errors(self.method) else 0,
                                   cfg.eval_growth_reports)
        """Held-out transitions per evaluation: ``eval_samples``, doubled while a settled graph has
        undecided entries (only where the graph has standard errors to be undecided)."""

    def ingest(self, batch: TransitionBatch) -> int:
        """Keep the held-out episodes of ``batch`` (ProtocolError if it does not fit the EnvSpec)."""
        check_fits(self.spec, batch)
        keep = heldout_mask(batch.worker_id, batch.episode_id, self.cfg.heldout_fraction)
        self.heldout.add(batch.state[keep], batch.action[keep], batch.next_state[keep], batch.reward[keep])
        if self.local is not None:
            self.local.add(batch, keep)
        return int(keep.sum())

    def load_weights(self, weights: Weights) -> None:
        """Remember the newest weights; the model is rebuilt only when its config changes. ValueError
        (before any model is built) for weights of another method or factor layout, whose configuration
        does not describe the tensors they carry, or whose version jumps past the bound
        (:class:`~services.runtime.accept.VersionGate`)."""
        if not self.versions.newer(self.kind, weights.version):
            return
        if weights.config_json != self.model_config:
            check_weights_config(weights.config_json, weights.tensors, self.kind, self.layout, model_from_config_json)
            self.model, self.model_config = model_from_config_json(weights.config_json).to(self.device), weights.config_json
            if self.method.global_graph is not None:
                self.threshold = float(self.method.global_graph.threshold(self.model))
            if self.method.reward_graph is not None:
                self.reward_threshold = float(self.method.reward_graph.threshold(self.model))
        import_tensors(self.model, weights.tensors)
        self.versions.accept(self.kind, weights.version)
        self.weights = weights

    @property
    def due(self) -> bool:
        return (self.method.global_graph is not None and self.weights is not None
                and self.weights.version > self.evaluated_version and self.heldout.size >= self.cfg.min_heldout)

    @property
    def local_due(self) -> bool:
        return self.local is not None and self.local.due(self.weights, self.cfg.min_heldout)

    def induced(self, batch: TransitionBatch) -> InducedGraphs | None:
        """The local graphs the current model induces for every step of ``batch`` (SkiLD: its estimator's
        scores at its threshold, :func:`causal.skild.induced_local_graphs`); None before any model."""
        if self.model is None or self.method.local_graph is None:
            return None
        state, action, next_state = (torch.from_numpy(x).to(self.device)
                                     for x in (batch.state, batch.action, batch.next_state))
        with torch.no_grad():
            scores = np.asarray(self.method.local_graph.scores(self.model, state, action, next_state))
        graphs = induced_local_graphs(scores, float(self.method.local_graph.threshold(self.model)),
                                      batch.state, batch.next_state)
        return InducedGraphs(kind=self.kind, worker_id=batch.worker_id, seq=batch.seq,
                             weights_version=self.weights.version, graphs=graphs.astype(np.uint8))

    def evaluate_local(self, every: bool = False,
                       progress: Callable[[int, int], None] | None = None) -> LocalGraphReport:
        """The method's local graphs of held-out transitions scored against their true local graphs
        (``every``: all of the kept ones, for the run's final report; ``progress(done, total)`` after
        each chunk of them)."""
        assert self.local is not None and self.model is not None and self.weights is not None
        return self.local.evaluate(self.model, self.weights, every, progress)

    def edge_scores(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor
                    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """The method's global edge scores (CDL: CMI in nats) of the current model on these transitions,
        their standard errors where the estimator gives them, and the permuted-input null with the
        standard error of ``cmi - null`` when ``bias`` asks for it (None otherwise)."""
        state, action, next_state = (t.to(self.device) for t in (state, action, next_state))
        estimator = self.method.global_graph
        if isinstance(estimator, EdgeEstimator):
            estimate = estimator.estimate(self.model, state, action, next_state, permute=self.permute)
            return tuple(None if x is None else x.astype(np.float32)  # type: ignore[return-value]
                         for x in (estimate.cmi, estimate.stderr, estimate.null, estimate.excess_stderr))
        return np.asarray(estimator.scores(self.model, state, action, next_state), dtype=np.float32), None, None, None

    def reward_scores(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor,
                      reward: torch.Tensor) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The method's reward-graph scores ``[d_S + 1]`` on these transitions and their standard errors
        where the estimator gives them (None without a reward graph)."""
        if self.method.reward_graph is None:
            return None, None
        state, action, next_state, reward = (t.to(self.device) for t in (state, action, next_state, reward))
        estimator = self.method.reward_graph
        if isinstance(estimator, RewardEdgeEstimator):
            estimate = estimator.estimate(self.model, state, action, next_state, reward)
            return estimate.cmi.astype(np.float32), estimate.stderr.astype(np.float32)
        return np.asarray(estimator.scores(self.model, state, action, next_state, reward), dtype=np.float32), None

    SMOOTHED = ("cmi_ema", "stderr_ema", "null_ema", "excess_stderr_ema", "reward_ema", "reward_stderr_ema")
    """The running estimates, in the order :meth:`edge_scores` and :meth:`reward_scores` return them."""

    def evaluate(self) -> GraphReport:
        """Edge scores for every edge (and the reward's, for a method with a reward graph) on held-out
        data, smoothed, decided and scored.

        The standard errors are averaged with the same weights as the scores. The standard deviation
        of a weighted sum is at most the weighted sum of the standard deviations whatever their
        correlation, and successive estimates are correlated (overlapping draws, similar models): the
        running standard error is an upper bound, never the smaller one independence would claim."""
        assert self.model is not None and self.weights is not None
        n = min(self.draw.size, self.heldout.size)
        index = self.heldout.rng.choice(self.heldout.size, n, replace=False)
        s, a, nxt, r = (torch.from_numpy(x[: self.heldout.size][index]) for x in
                        (self.heldout.state, self.heldout.action, self.heldout.next_state, self.heldout.reward))
        new = (*self.edge_scores(s, a, nxt), *self.reward_scores(s, a, nxt, r))
        alpha = self.previous_weight(self.weights.updates)
        for name, value in zip(self.SMOOTHED, new):
            old = getattr(self, name)
            setattr(self, name, value if old is None or value is None else alpha * old + (1 - alpha) * value)
        self.evaluated_version, self.evaluated_updates = self.weights.version, self.weights.updates
        report = self.report(n)
        if (undecided := report.undecided_count()) is not None:
            self.draw.observe(report.decided_graph(), undecided)
        return report

    def evaluate_final(self) -> GraphReport:
        """Algorithm 1, line 8: after training, the graph of the newest weights from CMI on every
        held-out transition, on its own (the running average, which mixes earlier models and
        draws of ``eval_samples``, is replaced by it)."""
        assert self.model is not None and self.weights is not None
        transitions = self.heldout.all()
        new = (*self.edge_scores(*transitions),
               *self.reward_scores(*transitions, torch.from_numpy(self.heldout.reward[: self.heldout.size])))
        for name, value in zip(self.SMOOTHED, new):
            setattr(self, name, value)
        self.evaluated_version, self.evaluated_updates = self.weights.version, self.weights.updates
        return self.report(self.heldout.size)

    def previous_weight(self, updates: int) -> float:
        """Weight of the running CMI average against an estimate from weights at ``updates``.

        The reference keeps an EMA of 0.999 per training update; we evaluate every few seconds, so
        the previous estimate keeps ``cmi_ema ** (updates since it)``: the same memory in updates
        however fast the learner runs or often we evaluate (about 1,000 updates at 0.999). Fewer
        updates than last time means a new model (a learner that started over): start afresh.
        """
        since = updates - self.evaluated_updates
        return float(self.cfg.cmi_ema ** max(since, 1)) if since >= 0 else 0.0

    def decide(self, cmi: np.ndarray, stderr: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """The edges (self-edges left out) under the configured rule, and the undecided entries
        (None without standard errors: only the fixed rule applies then)."""
        if stderr is None:
            return cmi >= self.threshold, None
        cfg = self.cfg
        estimate = EdgeEstimate(cmi, stderr, 0, self.null_ema, self.excess_stderr_ema)
        return decide(estimate, cfg.edge_rule, self.threshold, cfg.fdr, cfg.min_cmi, bias=cfg.bias)

    def tested_level(self, cmi: np.ndarray, stderr: np.ndarray) -> float:
        """The minimum effect size the fdr rule tested against: ``min_cmi``, or under ``bias`` split,
        mirror or mirror-permuted the level cut from this estimate (``causal.edge_tests.effect_level``)."""
        cfg = self.cfg
        estimate = EdgeEstimate(cmi, stderr, 0, self.null_ema, self.excess_stderr_ema)
        return effect_level(estimate, cfg.fdr, cfg.min_cmi, cfg.bias, cap=self.threshold)

    def decide_reward(self, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The reward's parents ``[d_S + 1]`` under the configured rule (fdr: at the same level and
        ``min_cmi``, against a fixed bias: the reward has no permuted null), and its undecided entries."""
        if self.reward_stderr_ema is None:
            return scores >= self.reward_threshold, None
        cfg = self.cfg
        return decide(EdgeEstimate(scores, self.reward_stderr_ema, 0), cfg.edge_rule, self.reward_threshold,
                      cfg.fdr, cfg.min_cmi)

    def report(self, num_heldout: int) -> GraphReport:
        cmi, threshold = self.cmi_ema.astype(np.float32), self.threshold
        stderr = None if self.stderr_ema is None else self.stderr_ema.astype(np.float32)
        edges, undecided = self.decide(cmi, stderr)
        adjacency = with_self_edges(edges).astype(np.uint8)
        rewards = None if self.reward_ema is None else self.reward_ema.astype(np.float32)
        parents, reward_undecided = (None, None) if rewards is None else self.decide_reward(rewards)
        parents = None if parents is None else parents.astype(np.uint8)
        abstraction = task_abstraction(self.method, adjacency, parents)
        truth = self.spec.global_graph
        metrics = (score_graph(cmi, truth, threshold, self.constant_factors, predicted=edges)
                   if truth is not None else {})
        if rewards is not None:
            metrics.update(reward_metrics(rewards, parents, self.spec.reward_parents))
            metrics.update(abstraction_metrics(adjacency, abstraction, truth, self.spec.reward_parents))
        w = self.weights
        tested = {} if undecided is None else {"undecided_entries": int(undecided.sum())}
        if reward_undecided is not None:
            tested["reward_undecided_entries"] = int(reward_undecided.sum())
        self.history.append({"env_steps": w.env_steps, "updates": w.updates, "time": time.time(), **metrics, **tested})
        rule = self.cfg.edge_rule if stderr is not None else "fixed"
        return GraphReport(kind=self.kind, weights_version=w.version, env_steps=w.env_steps, updates=w.updates,
                           factor_names=self.spec.factor_names, cmi=cmi, adjacency=adjacency,
                           threshold=threshold, controllable=abstraction.controllable,
                           action_relevant=abstraction.action_relevant,
                           action_irrelevant=abstraction.action_irrelevant, metrics=metrics,
                           true_graph=truth, num_heldout=num_heldout, timestamp=time.time(),
                           reward_scores=rewards, reward_parents=parents,
                           reward_threshold=self.reward_threshold if rewards is not None else 0.0,
                           true_reward_parents=self.spec.reward_parents if rewards is not None else None,
                           cmi_stderr=stderr, undecided=None if undecided is None else undecided.astype(np.uint8),
                           edge_rule=rule, fdr=self.cfg.fdr if rule == "fdr" else 0.0,
                           min_cmi=self.tested_level(cmi, stderr) if rule == "fdr" else 0.0,
                           bias=self.cfg.bias if rule == "fdr" else "fixed", cmi_null=self.null_ema,
                           reward_stderr=self.reward_stderr_ema,
                           reward_undecided=None if reward_undecided is None else reward_undecided.astype(np.uint8),
                           reward_min_cmi=self.cfg.min_cmi if reward_undecided is not None and self.cfg.edge_rule == "fdr"
                           else 0.0)

    def fingerprint(self) -> str:
        """What a checkpoint must match to be resumed: the environment (held-out data is env-specific);
        the method too, except CDL's, so checkpoints made before methods were plug-ins still resume."""
        method = {} if self.kind == "cdl" else {"method": self.kind}
        return json.dumps({"env": self.spec.env_id, "env_config": json.loads(self.spec.config_json), **method},
                          sort_keys=True)

    def checkpoint(self, path: Path) -> None:
        state = {"fingerprint": self.fingerprint(), "heldout": self.heldout.state_dict(),
                 "evaluated_version": self.evaluated_version, "evaluated_updates": self.evaluated_updates}
        if self.cmi_ema is not None:
            state["cmi_ema"] = torch.from_numpy(self.cmi_ema)
        for name in self.SMOOTHED[1:]:
            if getattr(self, name) is not None:
                state[name] = torch.from_numpy(getattr(self, name))
        if self.local is not None:
            state["local"] = self.local.state_dict()
        state["draw"] = self.draw.state_dict()
        save_checkpoint(state, path)

    def restore(self, path: Path) -> bool:
        saved = load_checkpoint(path)
        if saved is None:
            return False
        check_fingerprint(saved, self.fingerprint(), path)
        self.heldout.load_state_dict(saved["heldout"])
        self.evaluated_version = int(saved["evaluated_version"])
        self.versions.know(self.evaluated_version)
        self.evaluated_updates = int(saved.get("evaluated_updates", 0))
        if "cmi_ema" in saved:
            self.cmi_ema = saved["cmi_ema"].numpy()
        for name in self.SMOOTHED[1:]:
            if name in saved:
                setattr(self, name, saved[name].numpy())
        if self.local is not None and "local" in saved:
            self.local.load_state_dict(saved["local"])
        if "draw" in saved:
            self.draw.load_state_dict(saved["draw"])
        return True
