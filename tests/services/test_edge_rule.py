"""The evaluator's edge rules (issue 22): standard errors with the CMI, the FDR-tested graph, undecided
entries, and what reaches the wire, the summary and the run's flags."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.cdl import CDLConfig, CDLModel, model_config_json
from causal.edge_tests import EdgeEstimate, fdr_graph
from causal.factored import FactorLayout
from causal.graph_metrics import score_graph
from causal.method import export_tensors
from causal.methods.cdl import CMIGraph
from proto.codec import decode, encode
from proto.messages import EnvSpec, GraphReport, Weights
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.runtime.config import build_config, parse_config
from services.supervisor.config import RunConfig
from services.supervisor.report import graph_fields
from services.supervisor.wiring import resolve


def chain_spec():
    return EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3)).spec


def toy_spec() -> EnvSpec:
    """Three categorical factors: 0 -> 1 -> 2 and the action -> 0 (and the self-edges)."""
    truth = np.eye(3, 4, dtype=np.uint8)
    truth[1, 0] = truth[2, 1] = truth[0, 3] = 1
    return EnvSpec(env_id="toy", factor_names=("a", "b", "c"), factor_kinds=("categorical",) * 3,
                   factor_sizes=(5,) * 3, factor_objects=("a", "b", "c"), factor_locs=(0.0,) * 3,
                   factor_scales=(1.0,) * 3, action_kind="categorical", action_size=3, episode_length=10,
                   global_graph=truth)


def hand_made(core: GraphEvaluatorCore) -> tuple[np.ndarray, np.ndarray]:
    """An estimate on the toy graph with one entry of each kind: strong (0.5 +- 0.01), weak but sure
    (0.005 +- 0.0005), weak and unsure (0.005 +- 0.004), at the boundary of the fixed rule
    (0.021 +- 0.005), and noise (1e-4 +- 1e-4) everywhere else."""
    cmi = np.full(core.spec.global_graph.shape, 1e-4, np.float32)
    stderr = np.full(cmi.shape, 1e-4, np.float32)
    for cell, (mean, se) in {(1, 0): (0.5, 0.01), (2, 1): (0.005, 5e-4), (0, 3): (0.005, 4e-3),
                             (2, 3): (0.021, 5e-3)}.items():
        cmi[cell], stderr[cell] = mean, se
    core.cmi_ema, core.stderr_ema, core.threshold = cmi, stderr, 0.02
    core.weights = Weights(model="cdl", version=1, config_json="{}", env_steps=10, updates=1)
    return cmi, stderr


def test_fixed_rule_is_the_threshold_and_marks_intervals_across_it() -> None:
    core = GraphEvaluatorCore(GraphEvaluatorConfig(), toy_spec())
    cmi, _ = hand_made(core)
    report = core.report(num_heldout=100)
    off = ~np.eye(3, 4, dtype=bool)
    assert report.edge_rule == "fixed" and report.fdr == 0.0
    assert np.array_equal(report.adjacency.astype(bool), (cmi >= 0.02) | ~off)
    assert np.argwhere(report.undecided).tolist() == [[2, 3]]  # 0.021 +- 1.96 x 0.005 straddles 0.02
    assert report.metrics == score_graph(cmi, core.spec.global_graph, 0.02, ())  # scored as before the rules
    assert core.history[-1]["undecided_entries"] == 1


def test_fdr_rule_tests_each_entry_and_scores_the_tested_graph() -> None:
    core = GraphEvaluatorCore(GraphEvaluatorConfig(edge_rule="fdr", fdr=0.05, min_cmi=5e-4), toy_spec())
    cmi, stderr = hand_made(core)
    report = decode(encode(core.report(num_heldout=100)), GraphReport)
    expected = fdr_graph(EdgeEstimate(cmi, stderr, 100), 0.05, 5e-4) | np.eye(3, 4, dtype=bool)
    assert np.array_equal(report.adjacency.astype(bool), expected)
    assert report.adjacency[2, 1] and report.adjacency[2, 3]  # the weak sure edge, and the one at 0.021
    assert not report.adjacency[0, 3]  # weak and unsure: not an edge, and undecided
    assert np.argwhere(report.undecided).tolist() == [[0, 3]]
    assert (report.edge_rule, report.fdr, report.min_cmi) == ("fdr", 0.05, 5e-4)
    np.testing.assert_allclose(report.cmi_stderr, stderr)
    truth = core.spec.global_graph.astype(bool)
    found = report.adjacency.astype(bool) & ~np.eye(3, 4, dtype=bool)
    tp = (found & truth).sum()
    assert report.metrics["precision"] == pytest.approx(tp / found.sum())
    assert report.metrics["recall"] == pytest.approx(tp / (truth & ~np.eye(3, 4, dtype=bool)).sum())


def test_summary_carries_standard_errors_undecided_entries_and_the_rule() -> None:
    core = GraphEvaluatorCore(GraphEvaluatorConfig(edge_rule="fdr", min_cmi=5e-4), toy_spec())
    _, stderr = hand_made(core)
    fields = graph_fields(core.report(num_heldout=100))
    assert fields["edge_rule"] == "fdr" and fields["fdr"] == 0.05 and fields["min_cmi"] == 5e-4
    np.testing.assert_allclose(fields["cmi_stderr"], stderr, rtol=1e-2)
    assert fields["undecided"][0][3] == 1 and fields["undecided_entries"] == 1


def test_cdl_estimate_is_the_cmi_with_standard_errors_averaged_as_an_upper_bound(tmp_path) -> None:
    spec = chain_spec()
    cfg = GraphEvaluatorConfig(min_heldout=64, eval_samples=64, cmi_ema=0.99)
    core = GraphEvaluatorCore(cfg, spec)
    rng = np.random.default_rng(0)
    state = rng.integers(0, 5, (64, spec.state_dim)).astype(np.float32)
    action = rng.integers(0, 15, (64, 1)).astype(np.float32)
    core.heldout.add(state, action, np.roll(state, 1, axis=0))
    layout = FactorLayout.from_spec(spec)
    torch.manual_seed(0)
    stderrs = []
    for version, updates in ((1, 100), (2, 150)):
        model = CDLModel(layout, CDLConfig())
        core.load_weights(Weights(model="cdl", version=version, config_json=model_config_json(layout, CDLConfig()),
                                  env_steps=10, updates=updates, tensors=export_tensors(model)))
        held = tuple(torch.from_numpy(x[:64]) for x in (core.heldout.state, core.heldout.action, core.heldout.next_state))
        fresh = CMIGraph().estimate(core.model, *held)
        cmi = core.model.cmi(*held).numpy()
        np.testing.assert_allclose(fresh.cmi, cmi, rtol=1e-4, atol=1e-6 * max(1.0, float(np.abs(cmi).max())))
        gains = core.model.pointwise_cmi(*held).double().numpy()
        varying = ~core.model.constant_inputs(*held[:2]).numpy()
        np.testing.assert_allclose(fresh.stderr[:, varying], gains.std(0, ddof=1)[:, varying] / 8, rtol=1e-6)
        previous = None if core.stderr_ema is None else core.stderr_ema.copy()
        report = core.evaluate()
        stderrs.append((previous, fresh.stderr, report.cmi_stderr))
    previous, fresh, averaged = stderrs[1]
    weight = 0.99 ** 50
    np.testing.assert_allclose(averaged, weight * previous + (1 - weight) * fresh, rtol=1e-3)  # float32, 1e5 nats
    core.checkpoint(tmp_path / "ev.pt")
    again = GraphEvaluatorCore(cfg, spec)
    assert again.restore(tmp_path / "ev.pt") and np.array_equal(again.stderr_ema, core.stderr_ema)


def test_edge_rule_flags_are_declared_once_in_the_evaluator_section() -> None:
    cfg = parse_config(RunConfig, ["--evaluator-edge-rule", "fdr", "--evaluator-fdr", "0.1",
                                   "--evaluator-min-cmi", "0.001", "--stable-reports", "5"], environ={})
    assert (cfg.evaluator.edge_rule, cfg.evaluator.fdr, cfg.evaluator.min_cmi, cfg.stable_reports) == ("fdr", 0.1, 1e-3, 5)
    assert RunConfig().evaluator.edge_rule == "fixed"  # the chapter's threshold stays the default
    with pytest.raises(SystemExit):
        parse_config(RunConfig, ["--evaluator-edge-rule", "oracle"], environ={})
    with pytest.raises(ValueError, match="fdr"):
        build_config(RunConfig, evaluator_fdr=1.5)


def test_a_method_without_standard_errors_refuses_the_fdr_rule_and_the_stable_stop() -> None:
    # CBM's graphs have standard errors too since issue 22 item 4 (tests/services/test_edge_bias.py);
    # the modular model has no global graph at all
    with pytest.raises(ValueError, match="standard errors"):
        resolve(build_config(RunConfig, method="modular", evaluator_edge_rule="fdr"))
    with pytest.raises(ValueError, match="standard errors"):
        resolve(build_config(RunConfig, method="modular", stable_reports=3))
    with pytest.raises(ValueError, match="standard errors"):
        GraphEvaluatorCore(GraphEvaluatorConfig(method="modular", edge_rule="fdr"), chain_spec())
    assert resolve(build_config(RunConfig, evaluator_edge_rule="fdr", stable_reports=3, router_port=1)).stable_reports == 3
