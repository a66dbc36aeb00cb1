"""The evaluator's estimated bias (issue 22): the fdr rule tested against each entry's permuted-input
null (``--evaluator-bias permuted|pooled``), and CBM's dynamics and reward graphs with standard errors,
FDR decisions and undecided entries, on the wire and in the summary."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.cbm import CBMTrainer
from causal.cbm_config import CBMConfig
from causal.cdl import CDLConfig, CDLModel, model_config_json
from causal.edge_tests import decide, effect_level
from causal.factored import FactorLayout
from causal.method import export_tensors
from causal.methods.cdl import CMIGraph
from proto.codec import ProtocolError, decode, encode
from proto.messages import GraphReport, Weights
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.runtime.config import parse_config
from services.supervisor.config import RunConfig
from services.supervisor.report import graph_fields
from tests.services.test_edge_rule import chain_spec

torch.set_num_threads(1)


def filled_core(cfg: GraphEvaluatorConfig, n: int = 96) -> GraphEvaluatorCore:
    spec = chain_spec()
    core = GraphEvaluatorCore(cfg, spec)
    rng = np.random.default_rng(0)
    state = rng.integers(0, 5, (n, spec.state_dim)).astype(np.float32)
    action = rng.integers(0, 15, (n, 1)).astype(np.float32)
    core.heldout.add(state, action, np.roll(state, 1, axis=0), rng.normal(size=n).astype(np.float32))
    return core


@pytest.mark.parametrize("bias", ["permuted", "pooled", "mirror-permuted"])
def test_the_fdr_rule_against_the_permuted_null_reaches_the_report(bias: str, tmp_path) -> None:
    cfg = GraphEvaluatorConfig(edge_rule="fdr", bias=bias, min_heldout=64, seed=3)
    core = filled_core(cfg)
    layout = FactorLayout.from_spec(core.spec)
    torch.manual_seed(0)
    model = CDLModel(layout, CDLConfig())
    core.load_weights(Weights(model="cdl", version=1, config_json=model_config_json(layout, CDLConfig()),
                              env_steps=10, updates=100, tensors=export_tensors(model)))
    report = decode(encode(core.evaluate_final()), GraphReport)
    held = core.heldout.all()[:3]
    estimate = CMIGraph().estimate(core.model, *held, permute=torch.Generator().manual_seed(cfg.seed + 2))
    edges, undecided = decide(estimate, "fdr", report.threshold, cfg.fdr, cfg.min_cmi, bias=bias)
    off = ~np.eye(*edges.shape, dtype=bool)
    assert report.bias == bias and report.edge_rule == "fdr"
    np.testing.assert_allclose(report.cmi_null, estimate.null, rtol=1e-4, atol=1e-6)
    assert np.array_equal(report.adjacency.astype(bool) & off, edges)
    assert np.array_equal(report.undecided.astype(bool), undecided)
    if bias == "mirror-permuted":   # the report's min_cmi is the level its excess was cut at
        level = effect_level(estimate, cfg.fdr, cfg.min_cmi, bias, cap=report.threshold)
        assert report.min_cmi == pytest.approx(level, rel=1e-4)
    fields = graph_fields(report)
    assert fields["bias"] == bias and np.shape(fields["cmi_null"]) == edges.shape
    core.checkpoint(tmp_path / "ev.pt")
    again = GraphEvaluatorCore(cfg, core.spec)
    assert again.restore(tmp_path / "ev.pt") and np.array_equal(again.null_ema, core.null_ema)


def test_a_report_with_an_estimated_bias_needs_its_null() -> None:
    core = filled_core(GraphEvaluatorConfig(edge_rule="fdr", bias="permuted", min_heldout=64))
    layout = FactorLayout.from_spec(core.spec)
    core.load_weights(Weights(model="cdl", version=1, config_json=model_config_json(layout, CDLConfig()),
                              env_steps=10, updates=100, tensors=export_tensors(CDLModel(layout, CDLConfig()))))
    report = core.evaluate_final()
    with pytest.raises(ProtocolError, match="cmi_null"):
        decode(encode(GraphReport(**{**report.__dict__, "cmi_null": None})), GraphReport)
    with pytest.raises(ProtocolError, match="bias"):
        decode(encode(GraphReport(**{**report.__dict__, "bias": "guessed"})), GraphReport)
    cfg = parse_config(RunConfig, ["--evaluator-edge-rule", "fdr", "--evaluator-bias", "pooled"], environ={})
    assert cfg.evaluator.bias == "pooled" and RunConfig().evaluator.bias == "fixed"
    with pytest.raises(SystemExit):
        parse_config(RunConfig, ["--evaluator-bias", "guessed"], environ={})


def cbm_core(cfg: GraphEvaluatorConfig) -> GraphEvaluatorCore:
    core = filled_core(cfg)
    trainer = CBMTrainer(FactorLayout.from_spec(core.spec),
                         CBMConfig(eval_negatives=64, feature_hidden=8, feature_dim=8, predictor_hidden=8, embed_dim=8,
                                   candidate_hidden=8, reward_hidden=8), seed=0)
    core.load_weights(Weights(model="cbm", version=1, config_json=trainer.config_json(), env_steps=10, updates=5,
                              tensors=export_tensors(trainer.model)))
    return core


@pytest.mark.parametrize("bias", ["fixed", "mirror"])
def test_cbm_reports_standard_errors_fdr_decisions_and_undecided_entries_of_both_graphs(bias: str) -> None:
    """Both graphs' tests reach the report; the reward row's effect size is the configured ``min_cmi``
    (``reward_min_cmi``) whatever level the dynamics graph used (under ``mirror``: its own)."""
    cfg = GraphEvaluatorConfig(method="cbm", edge_rule="fdr", min_heldout=64, min_cmi=5e-3, bias=bias)
    core = cbm_core(cfg)
    report = decode(encode(core.evaluate_final()), GraphReport)
    assert report.reward_min_cmi == 5e-3 and (bias == "mirror" or report.min_cmi == 5e-3)
    d = len(report.factor_names)
    assert report.edge_rule == "fdr" and report.cmi_stderr.shape == (d, d + 1) and report.undecided is not None
    assert report.reward_stderr.shape == (d + 1,) and (report.reward_stderr > 0).any()
    parents, open_ = core.decide_reward(report.reward_scores)
    assert np.array_equal(report.reward_parents.astype(bool), parents)
    assert np.array_equal(report.reward_undecided.astype(bool), open_)
    fields = graph_fields(report)
    assert set(fields["reward_graph"]["stderr"]) == set(report.factor_names) | {"action"}
    assert "undecided" in fields["reward_graph"] and "cmi_stderr" in fields
    assert fields["reward_graph"]["min_cmi"] == 5e-3
    with pytest.raises(ProtocolError, match="reward_min_cmi"):
        decode(encode(GraphReport(**{**report.__dict__, "reward_stderr": None, "reward_undecided": None})), GraphReport)
    with pytest.raises(ProtocolError, match="reward_min_cmi"):
        decode(encode(GraphReport(**{**report.__dict__, "reward_min_cmi": float("nan")})), GraphReport)
    assert core.history[-1]["reward_undecided_entries"] == int(open_.sum())


def test_cbm_implicit_dynamics_refuse_the_permuted_null() -> None:
    core = cbm_core(GraphEvaluatorConfig(method="cbm", edge_rule="fdr", bias="permuted", min_heldout=64))
    with pytest.raises(ValueError, match="no permuted-input null"):
        core.evaluate_final()


def test_a_run_asking_for_a_null_its_method_lacks_is_refused_before_it_starts() -> None:
    from services.runtime.config import build_config
    from services.supervisor.wiring import resolve

    for bias in ("permuted", "pooled", "global", "mirror-permuted"):
        with pytest.raises(ValueError, match=f"--evaluator-bias {bias}: CBM's implicit dynamics have no permuted-input null"):
            resolve(build_config(RunConfig, method="cbm", env="chemical-distractors", evaluator_bias=bias))
        with pytest.raises(ValueError, match="'modular' has no standard errors"):
            resolve(build_config(RunConfig, method="modular", evaluator_bias=bias))
    explicit = resolve(build_config(RunConfig, method="cbm", env="chemical-distractors", evaluator_bias="permuted",
                                    cbm_dynamics="explicit", router_port=1))
    assert explicit.evaluator.bias == "permuted"
    assert resolve(build_config(RunConfig, evaluator_bias="global", router_port=1)).evaluator.bias == "global"


@pytest.mark.parametrize("bias", ["split", "mirror"])
def test_the_estimated_level_reaches_the_report_without_a_null(bias: str, tmp_path) -> None:
    """``--evaluator-bias split`` or ``mirror``: no permuted null is drawn or sent; the report's edges and
    undecided entries are ``decide``'s under that rule and its ``min_cmi`` is the level the rule used."""
    cfg = GraphEvaluatorConfig(edge_rule="fdr", bias=bias, min_heldout=64, seed=3)
    core = filled_core(cfg)
    assert core.permute is None
    layout = FactorLayout.from_spec(core.spec)
    torch.manual_seed(0)
    core.load_weights(Weights(model="cdl", version=1, config_json=model_config_json(layout, CDLConfig()),
                              env_steps=10, updates=100, tensors=export_tensors(CDLModel(layout, CDLConfig()))))
    report = decode(encode(core.evaluate_final()), GraphReport)
    assert report.bias == bias and report.cmi_null is None and report.edge_rule == "fdr"
    estimate = CMIGraph().estimate(core.model, *core.heldout.all()[:3])
    edges, undecided = decide(estimate, "fdr", report.threshold, cfg.fdr, cfg.min_cmi, bias=bias)
    assert np.array_equal(report.adjacency.astype(bool) & ~np.eye(*edges.shape, dtype=bool), edges)
    assert np.array_equal(report.undecided.astype(bool), undecided)
    level = effect_level(estimate, cfg.fdr, cfg.min_cmi, bias, cap=report.threshold)
    assert report.min_cmi == pytest.approx(level, rel=1e-4) and graph_fields(report)["bias"] == bias


@pytest.mark.parametrize("bias", ["split", "mirror"])
def test_the_estimated_level_needs_standard_errors_but_no_null(bias: str) -> None:
    from services.runtime.config import build_config
    from services.supervisor.wiring import resolve

    cbm = resolve(build_config(RunConfig, method="cbm", env="chemical-distractors", evaluator_bias=bias,
                               evaluator_edge_rule="fdr", router_port=1))
    assert cbm.evaluator.bias == bias
    with pytest.raises(ValueError, match=f"--evaluator-bias {bias} needs a global graph with standard errors"):
        resolve(build_config(RunConfig, method="modular", evaluator_bias=bias, router_port=1))
    cfg = parse_config(RunConfig, ["--evaluator-edge-rule", "fdr", "--evaluator-bias", bias], environ={})
    assert cfg.evaluator.bias == bias


def test_the_summary_keeps_the_small_cmi_entries_the_level_is_read_from() -> None:
    """Seen reading live ``mirror`` runs: the summary rounded the CMI to 5 decimals, which made most
    of a long-trained model's non-edges 0 and hid the negative side ``mirror`` reads its level from.
    It keeps 4 significant digits, so the summary's table gives the report's level back."""
    from causal.edge_tests import EdgeEstimate, mirror_level

    rng = np.random.default_rng(0)
    n = 12
    cmi = (rng.standard_t(3, (n, n + 1)) * 1e-6).astype(np.float32)   # non-edges at 1e-7 .. 1e-5 nats
    cmi[np.arange(n), (np.arange(n) + 1) % n] = 3e-3                     # one edge per output
    stderr = np.full_like(cmi, 1e-6)
    level = mirror_level(EdgeEstimate(cmi, stderr, 2000), 0.05, cap=0.02)
    report = GraphReport(kind="cdl", weights_version=1, env_steps=10, updates=10,
                         factor_names=tuple(f"f{i}" for i in range(n)), cmi=cmi,
                         adjacency=(cmi >= level).astype(np.uint8), threshold=0.02, controllable=(),
                         action_relevant=(), action_irrelevant=(), metrics={}, timestamp=1.0,
                         undecided=np.zeros_like(cmi, np.uint8), cmi_stderr=stderr, edge_rule="fdr", fdr=0.05,
                         min_cmi=level, bias="mirror")
    fields = graph_fields(report)
    kept = np.asarray(fields["cmi"], np.float64)
    np.testing.assert_allclose(kept, cmi, rtol=1e-3, atol=0)
    assert (np.sign(kept) == np.sign(cmi)).all()
    again = mirror_level(EdgeEstimate(kept, np.asarray(fields["cmi_stderr"]), 2000), 0.05, cap=0.02)
    assert again == pytest.approx(fields["min_cmi"], rel=1e-3)
