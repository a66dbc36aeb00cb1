"""The evaluator's draw of held-out transitions grows where the data decides (issue 22, item 3): a
settled graph with undecided entries doubles the draw, a changing one does not."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from causal.cdl import CDLConfig, CDLModel, model_config_json
from causal.factored import FactorLayout
from causal.method import export_tensors
from proto.messages import Weights
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import EvaluationDraw, GraphEvaluatorCore
from services.runtime.config import build_config, parse_config
from services.supervisor.config import RunConfig


def test_draw_doubles_only_for_a_settled_graph_with_undecided_entries() -> None:
    draw = EvaluationDraw(base=100, most=500, reports=3)
    a, b = b"graph a", b"graph b"
    assert [draw.observe(g, 2) for g in (a, b, a, b, a)] == [False] * 5  # a changing graph: the model moves
    assert draw.size == 100
    assert [draw.observe(a, 0) for _ in range(5)] == [False] * 5  # settled and decided: nothing to grow for
    assert draw.size == 100
    assert draw.observe(a, 1) and draw.size == 200  # the 6th report of a: undecided, so it grows
    assert [draw.observe(a, 1) for _ in range(3)] == [False, False, True] and draw.size == 400  # counted afresh
    assert [draw.observe(a, 1) for _ in range(3)] == [False, False, True] and draw.size == 500  # capped
    assert not any(draw.observe(a, 1) for _ in range(6)) and draw.size == 500
    assert not draw.observe(b, 0) and draw.size == 500  # never shrinks


def test_draw_that_may_not_grow_and_its_checkpoint() -> None:
    fixed = EvaluationDraw(base=2_000, most=1_000, reports=1)  # most <= base: never grows
    assert not any(fixed.observe(b"g", 5) for _ in range(4)) and fixed.size == 2_000
    draw = EvaluationDraw(base=100, most=800, reports=1)
    draw.observe(b"g", 1)
    again = EvaluationDraw(base=100, most=800, reports=1)
    again.load_state_dict(draw.state_dict())
    assert again.size == draw.size == 200
    again.load_state_dict({"size": 10_000})  # a checkpoint from a run with a larger cap: clamped
    assert again.size == 800


def test_flags_and_their_validation() -> None:
    cfg = parse_config(RunConfig, ["--evaluator-eval-samples-max", "8000", "--evaluator-eval-growth-reports", "5"],
                       environ={})
    assert (cfg.evaluator.eval_samples_max, cfg.evaluator.eval_growth_reports) == (8000, 5)
    with pytest.raises(ValueError, match="eval_growth_reports"):
        GraphEvaluatorConfig(eval_growth_reports=0)
    with pytest.raises(ValueError, match="eval_samples_max"):
        GraphEvaluatorConfig(eval_samples_max=-1)


def test_a_method_without_standard_errors_keeps_its_draw() -> None:
    spec = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3)).spec
    core = GraphEvaluatorCore(GraphEvaluatorConfig(method="elden", eval_samples=64, eval_samples_max=512), spec)
    assert core.draw.most == core.draw.base == 64


def test_evaluator_draws_more_while_its_settled_graph_has_undecided_entries(tmp_path) -> None:
    """One model loaded again and again (one update apart, so the running CMI keeps 0.999 of itself and
    the graph holds still); an untrained model's CMI estimates are wide, so under the fdr rule some
    entries' intervals reach its level. The draw doubles every 2 reports up to 256, and a checkpoint
    keeps it."""
    spec = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3)).spec
    layout = FactorLayout.from_spec(spec)
    rng = np.random.default_rng(0)
    state = rng.integers(0, 5, (512, spec.state_dim)).astype(np.float32)
    action = rng.integers(0, 15, (512, 1)).astype(np.float32)
    torch.manual_seed(0)
    model = CDLModel(layout, CDLConfig())
    cfg = GraphEvaluatorConfig(min_heldout=64, eval_samples=64, eval_samples_max=256, eval_growth_reports=2,
                               edge_rule="fdr")
    core = GraphEvaluatorCore(cfg, spec)
    core.heldout.add(state, action, np.roll(state, 1, axis=0))
    drawn, undecided, graphs = [], [], set()
    for version in range(1, 8):
        core.load_weights(Weights(model="cdl", version=version, config_json=model_config_json(layout, CDLConfig()),
                                  env_steps=10, updates=version, tensors=export_tensors(model)))
        report = core.evaluate()
        drawn.append(report.num_heldout)
        undecided.append(int(report.undecided.sum()))
        graphs.add(report.adjacency.tobytes())
    assert len(graphs) == 1 and min(undecided) > 0  # the premise: settled, and undecided throughout
    assert drawn == [64, 64, 128, 128, 256, 256, 256]
    core.checkpoint(tmp_path / "ev.pt")
    again = GraphEvaluatorCore(cfg, spec)
    assert again.restore(tmp_path / "ev.pt") and again.draw.size == 256
