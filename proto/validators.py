"""The cross-field rules of every message, run by :func:`proto.codec.decode` once each field has its
type: shapes that must agree, indices in range, counters that cannot be negative, names from fixed
sets. Each raises :class:`proto.limits.ProtocolError` with a bounded reason."""
from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any, Final

import numpy as np

from proto.limits import KEY_SEGMENT, MAX_LOCAL_EXAMPLES, MAX_STEPS, ProtocolError, require, short
from proto.messages import ACTION_KINDS, BIASES, CONTROL_COMMANDS, EDGE_RULES, FACTOR_KINDS, NULL_BIASES, SKILL_PHASES
from proto.messages import (Control, EnvSpec, FrameBatch, GraphReport, InducedGraphs, LatentActions, LocalGraphReport,
                            ScoredBatch, ServiceStats, SkillBatch, TransitionBatch, Weights)


def _check_counters(msg: Any, *names: str) -> None:
    for name in names:
        value = getattr(msg, name)
        require(value >= 0, "bad_field", f"{msg.TYPE}.{name}: {value} < 0")


def _check_graph(graph: np.ndarray, shape: tuple[int, ...], path: str) -> None:
    require(graph.shape == shape, "inconsistent", f"{path}: shape {graph.shape}, want {shape}")
    require(bool((graph <= 1).all()), "bad_array", f"{path}: values outside {{0, 1}}")


def _check_env_spec(m: EnvSpec) -> None:
    n = len(m.factor_names)
    require(n >= 1, "bad_field", "EnvSpec.factor_names: empty")
    require(all(m.factor_names), "bad_field", "EnvSpec.factor_names: empty name")
    require(len(set(m.factor_names)) == n, "bad_field", "EnvSpec.factor_names: duplicates")
    for name in ("factor_kinds", "factor_sizes", "factor_objects", "factor_locs", "factor_scales"):
        count = len(getattr(m, name))
        require(count == n, "inconsistent", f"EnvSpec.{name}: {count} entries for {n} factors")
    for kind, size in zip(m.factor_kinds, m.factor_sizes):
        require(kind in FACTOR_KINDS, "bad_field", f"EnvSpec.factor_kinds: {short(kind)}")
        least = 2 if kind == "categorical" else 1
        require(size >= least, "bad_field", f"EnvSpec.factor_sizes: {kind} of size {size}")
    require(all(s > 0 for s in m.factor_scales), "bad_field", "EnvSpec.factor_scales: <= 0")
    ok = m.action_kind in ACTION_KINDS
    require(ok, "bad_field", f"EnvSpec.action_kind: {short(m.action_kind)}")
    require(m.action_size >= 1, "bad_field", f"EnvSpec.action_size: {m.action_size}")
    require(m.episode_length >= 1, "bad_field", f"EnvSpec.episode_length: {m.episode_length}")
    if m.global_graph is not None:
        _check_graph(m.global_graph, (n, n + 1), "EnvSpec.global_graph")
    if m.reward_parents is not None:
        _check_graph(m.reward_parents, (n + 1,), "EnvSpec.reward_parents")
    _check_bounds(m)


def _check_bounds(m: EnvSpec) -> None:
    require((m.state_low is None) == (m.state_high is None), "inconsistent",
             "EnvSpec: state_low and state_high come together")
    if m.state_low is None:
        return
    for name in ("state_low", "state_high"):
        shape = getattr(m, name).shape
        require(shape == (m.state_dim,), "inconsistent", f"EnvSpec.{name}: shape {shape}, state_dim {m.state_dim}")
    require(bool((m.state_low <= m.state_high).all()), "inconsistent", "EnvSpec: state_low above state_high")


def _check_transitions(m: TransitionBatch) -> None:
    steps = m.state.shape[0]
    require(steps >= 1, "bad_field", "TransitionBatch: empty batch")
    require(steps <= MAX_STEPS, "too_large", f"TransitionBatch: {steps} steps > {MAX_STEPS}")
    same = m.next_state.shape == m.state.shape
    require(same, "inconsistent", f"TransitionBatch.next_state: shape {m.next_state.shape}")
    ok = m.action.shape[0] == steps
    require(ok, "inconsistent", f"TransitionBatch.action: shape {m.action.shape}")
    for name in ("reward", "terminated", "truncated", "episode_id", "step"):
        shape = getattr(m, name).shape
        require(shape == (steps,), "inconsistent", f"TransitionBatch.{name}: shape {shape}")
    if m.local_graph is not None:
        d = m.local_graph.shape[1]
        _check_graph(m.local_graph, (steps, d, d + 1), "TransitionBatch.local_graph")
    if m.option is not None:
        require(m.option.shape == (steps,), "inconsistent", f"TransitionBatch.option: shape {m.option.shape}")
        require(bool((m.option >= -1).all()), "bad_array", "TransitionBatch.option: below -1")
    _check_counters(m, "seq", "policy_version")
    ok = KEY_SEGMENT.fullmatch(m.worker_id) is not None
    require(ok, "bad_field", f"TransitionBatch.worker_id: {short(m.worker_id)}")


def _check_frames(m: FrameBatch) -> None:
    steps, count = m.state_frame.shape[0], m.frames.shape[0]
    require(steps >= 1, "bad_field", "FrameBatch: empty batch")
    require(steps <= MAX_STEPS, "too_large", f"FrameBatch: {steps} steps > {MAX_STEPS}")
    require(1 <= count <= 2 * steps, "inconsistent", f"FrameBatch.frames: {count} frames for {steps} steps")
    ok = m.frames.shape[3] == 3 and min(m.frames.shape[1:3]) >= 1
    require(ok, "inconsistent", f"FrameBatch.frames: shape {m.frames.shape}, want [F, H, W, 3]")
    for name in ("next_frame", "reward", "terminated", "truncated", "episode_id", "step"):
        shape = getattr(m, name).shape
        require(shape == (steps,), "inconsistent", f"FrameBatch.{name}: shape {shape}")
    require(m.action.shape[0] == steps, "inconsistent", f"FrameBatch.action: shape {m.action.shape}")
    for name in ("state_frame", "next_frame"):
        index = getattr(m, name)
        require(bool(((index >= 0) & (index < count)).all()), "inconsistent", f"FrameBatch.{name}: outside [0, {count})")
    if m.labels is not None:
        ok = m.labels.shape == m.frames.shape[:3]
        require(ok, "inconsistent", f"FrameBatch.labels: shape {m.labels.shape}, frames {m.frames.shape}")
    _check_counters(m, "seq", "policy_version")
    ok = KEY_SEGMENT.fullmatch(m.worker_id) is not None
    require(ok, "bad_field", f"FrameBatch.worker_id: {short(m.worker_id)}")


def _check_scored(m: ScoredBatch) -> None:
    shape, want = m.intrinsic_reward.shape, (len(m.transitions),)
    require(shape == want, "inconsistent", f"ScoredBatch.intrinsic_reward: {shape}, want {want}")
    _check_counters(m, "weights_version")


def _check_weights(m: Weights) -> None:
    _check_counters(m, "version", "updates", "env_steps")
    require(all(m.tensors), "bad_field", "Weights.tensors: empty tensor name")
    try:
        config = json.loads(m.config_json)
    except (ValueError, RecursionError):
        raise ProtocolError("bad_field", "Weights.config_json: not JSON") from None
    require(isinstance(config, dict), "bad_field", "Weights.config_json: not a JSON object")


def _check_graph_report(m: GraphReport) -> None:
    d = len(m.factor_names)
    shape = (d, d + 1)
    require(m.cmi.shape == shape, "inconsistent", f"GraphReport.cmi: {m.cmi.shape}, want {shape}")
    _check_graph(m.adjacency, shape, "GraphReport.adjacency")
    if m.true_graph is not None:
        _check_graph(m.true_graph, shape, "GraphReport.true_graph")
    classes = m.controllable + m.action_relevant + m.action_irrelevant
    ok = all(0 <= i < d for i in classes)
    require(ok, "bad_field", f"GraphReport: factor index outside [0, {d})")
    require(len(set(classes)) == len(classes), "inconsistent", "GraphReport: classes overlap")
    _check_counters(m, "weights_version", "env_steps", "updates", "num_heldout")
    _check_reward_graph(m, d)
    _check_edge_tests(m, shape)


def _check_edge_tests(m: GraphReport, shape: tuple[int, int]) -> None:
    """Standard errors and undecided entries come together, shaped like the CMI; the rule is known."""
    ok = (m.cmi_stderr is None) == (m.undecided is None)
    require(ok, "inconsistent", "GraphReport: cmi_stderr and undecided come together")
    if m.cmi_stderr is not None:
        got = m.cmi_stderr.shape
        require(got == shape, "inconsistent", f"GraphReport.cmi_stderr: {got}, want {shape}")
        require(bool((m.cmi_stderr >= 0).all()), "bad_array", "GraphReport.cmi_stderr: negative")
        _check_graph(m.undecided, shape, "GraphReport.undecided")
    require(m.edge_rule in EDGE_RULES, "bad_field", f"GraphReport.edge_rule: {short(m.edge_rule)}")
    ok = m.edge_rule == "fixed" or m.cmi_stderr is not None
    require(ok, "inconsistent", "GraphReport: edge_rule fdr without cmi_stderr")
    require(0.0 <= m.fdr < 1.0 and m.min_cmi >= 0.0, "bad_field", f"GraphReport: fdr {m.fdr}, min_cmi {m.min_cmi}")
    require(m.bias in BIASES, "bad_field", f"GraphReport.bias: {short(m.bias)}")
    ok = m.bias == "fixed" or (m.edge_rule == "fdr" and (m.bias not in NULL_BIASES or m.cmi_null is not None))
    require(ok, "inconsistent", f"GraphReport: bias {m.bias} without the fdr rule and cmi_null")
    if m.cmi_null is not None:
        require(m.cmi_null.shape == shape, "inconsistent", f"GraphReport.cmi_null: {m.cmi_null.shape}, want {shape}")


def _check_reward_graph(m: GraphReport, d: int) -> None:
    """Reward scores and parents come together, one entry per factor and the action."""
    ok = (m.reward_scores is None) == (m.reward_parents is None)
    require(ok, "inconsistent", "GraphReport: reward_scores and reward_parents come together")
    if m.reward_scores is not None:
        shape = m.reward_scores.shape
        require(shape == (d + 1,), "inconsistent", f"GraphReport.reward_scores: {shape}, want {(d + 1,)}")
        _check_graph(m.reward_parents, (d + 1,), "GraphReport.reward_parents")
    if m.true_reward_parents is not None:
        _check_graph(m.true_reward_parents, (d + 1,), "GraphReport.true_reward_parents")
    ok = (m.reward_stderr is None) == (m.reward_undecided is None) and (m.reward_stderr is None or m.reward_scores is not None)
    require(ok, "inconsistent", "GraphReport: reward_stderr and reward_undecided come together, with reward_scores")
    if m.reward_stderr is not None:
        got = m.reward_stderr.shape
        require(got == (d + 1,), "inconsistent", f"GraphReport.reward_stderr: {got}, want {(d + 1,)}")
        require(bool((m.reward_stderr >= 0).all()), "bad_array", "GraphReport.reward_stderr: negative")
        _check_graph(m.reward_undecided, (d + 1,), "GraphReport.reward_undecided")
    ok = bool(np.isfinite(m.reward_min_cmi)) and m.reward_min_cmi >= 0.0
    ok = ok and (m.reward_stderr is not None or m.reward_min_cmi == 0.0)
    require(ok, "bad_field", f"GraphReport.reward_min_cmi: {m.reward_min_cmi} (finite, >= 0, and 0 without reward_stderr)")


def _check_local_report(m: LocalGraphReport) -> None:
    d = len(m.factor_names)
    k = m.scores.shape[0]
    require(k <= MAX_LOCAL_EXAMPLES, "too_large", f"LocalGraphReport: {k} examples > {MAX_LOCAL_EXAMPLES}")
    shape = (k, d, d + 1)
    require(m.scores.shape == shape, "inconsistent", f"LocalGraphReport.scores: {m.scores.shape}, want {shape}")
    _check_graph(m.truth, shape, "LocalGraphReport.truth")
    _check_counters(m, "weights_version", "env_steps", "updates", "num_transitions")


def _check_skill_batch(m: SkillBatch) -> None:
    steps = (len(m.transitions),)
    for name in ("slot", "b", "started"):
        shape = getattr(m, name).shape
        require(shape == steps, "inconsistent", f"SkillBatch.{name}: shape {shape}, want {steps}")
    require(m.phase in SKILL_PHASES, "bad_field", f"SkillBatch.phase: {short(m.phase)}")
    require(bool((m.slot >= -1).all()), "bad_array", "SkillBatch.slot: below -1")
    require(bool((m.b >= 0).all()), "bad_array", "SkillBatch.b: negative")


def _check_induced(m: InducedGraphs) -> None:
    t, d = m.graphs.shape[0], m.graphs.shape[1]
    require(1 <= t <= MAX_STEPS, "bad_field", f"InducedGraphs: {t} steps")
    _check_graph(m.graphs, (t, d, d + 1), "InducedGraphs.graphs")
    _check_counters(m, "seq", "weights_version")
    for name in ("kind", "worker_id"):
        ok = KEY_SEGMENT.fullmatch(getattr(m, name)) is not None
        require(ok, "bad_field", f"InducedGraphs.{name}: {short(getattr(m, name))}")


def _check_latent_actions(m: LatentActions) -> None:
    t = m.mean.shape[0]
    require(1 <= t <= MAX_STEPS, "bad_field", f"LatentActions: {t} steps")
    require(min(m.mean.shape[1:]) >= 1, "bad_field", f"LatentActions.mean: shape {m.mean.shape}")
    require(m.log_sigma.shape == m.mean.shape, "inconsistent",
            f"LatentActions.log_sigma: shape {m.log_sigma.shape}, mean {m.mean.shape}")
    for name in ("episode_id", "step"):
        shape = getattr(m, name).shape
        require(shape == (t,), "inconsistent", f"LatentActions.{name}: shape {shape}, want {(t,)}")
    _check_counters(m, "seq", "weights_version")
    for name in ("kind", "worker_id"):
        ok = KEY_SEGMENT.fullmatch(getattr(m, name)) is not None
        require(ok, "bad_field", f"LatentActions.{name}: {short(getattr(m, name))}")


def _check_control(m: Control) -> None:
    require(m.command in CONTROL_COMMANDS, "bad_field", f"Control.command: {short(m.command)}")


def _check_stats(m: ServiceStats) -> None:
    require(bool(m.service), "bad_field", "ServiceStats.service: empty")
    require(bool(m.instance), "bad_field", "ServiceStats.instance: empty")


VALIDATORS: Final[dict[type, Callable[[Any], None]]] = {
    EnvSpec: _check_env_spec,
    TransitionBatch: _check_transitions,
    FrameBatch: _check_frames,
    ScoredBatch: _check_scored,
    Weights: _check_weights,
    GraphReport: _check_graph_report,
    LocalGraphReport: _check_local_report,
    SkillBatch: _check_skill_batch,
    InducedGraphs: _check_induced,
    LatentActions: _check_latent_actions,
    Control: _check_control,
    ServiceStats: _check_stats,
}
