"""graph-evaluator core: its reports carry the paper's scores and the identifiable ones."""
from __future__ import annotations

import numpy as np

from envs.manipulation_layout import CONSTANT_FACTORS, FACTOR_NAMES, FACTOR_OBJECTS
from envs.manipulation_truth import global_graph
from proto.messages import EnvSpec, Weights
from services.runtime.config import build_config
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore, constant_factor_indices


def _manipulation_spec() -> EnvSpec:
    """The manipulation EnvSpec without building the simulator (its layout and truth are pure data)."""
    n = len(FACTOR_NAMES)
    return EnvSpec(env_id="manipulation", factor_names=FACTOR_NAMES, factor_kinds=("continuous",) * n,
                   factor_sizes=(1,) * n, factor_objects=FACTOR_OBJECTS, factor_locs=(0.0,) * n,
                   factor_scales=(1.0,) * n, action_kind="continuous", action_size=4, episode_length=250,
                   global_graph=global_graph())


def _report_metrics(spec: EnvSpec, cmi: np.ndarray) -> dict[str, float]:
    core = GraphEvaluatorCore(GraphEvaluatorConfig(), spec)
    core.cmi_ema, core.threshold = cmi.astype(np.float32), 0.02
    core.weights = Weights(model="cdl", version=1, config_json="{}", env_steps=10, updates=1)
    return core.report(num_heldout=100).metrics


def test_manipulation_reports_score_the_identifiable_edges_apart() -> None:
    spec = _manipulation_spec()
    constant = constant_factor_indices(spec)
    assert [spec.factor_names[i] for i in constant] == list(CONSTANT_FACTORS)
    truth = spec.global_graph
    cmi = np.where(truth == 1, 0.5, 1e-4)
    cmi[:, list(constant)] = 0.0  # what data can say about a constant cause: nothing
    m = _report_metrics(spec, cmi)
    assert m["unidentifiable_true_edges"] == 16.0  # eef, grp, mov (8 rows) <- unm.z, rand.z
    assert m["identifiable_f1"] == 1.0 and m["identifiable_accuracy"] == 1.0
    assert m["identifiable_best_threshold_f1"] == 1.0
    assert m["f1"] < 1.0 and m["recall"] < 1.0 and m["precision"] == 1.0
    # Table 3.1's scoring: the 23 self-edges count as found, the 16 from constant columns as missed
    assert m["with_self_recall"] == (135 - 16) / 135 and m["with_self_precision"] == 1.0


def test_chemical_reports_identical_identifiable_scores() -> None:
    spec = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3)).spec
    assert constant_factor_indices(spec) == ()
    rng = np.random.default_rng(0)
    m = _report_metrics(spec, rng.uniform(0, 0.05, spec.global_graph.shape))
    paper = {k: v for k, v in m.items() if not k.startswith(("identifiable_", "unidentifiable_", "with_self_"))}
    assert {k: m[f"identifiable_{k}"] for k in paper} == paper and m["unidentifiable_true_edges"] == 0.0


def test_cmi_average_keeps_the_reference_memory_per_learner_update() -> None:
    core = GraphEvaluatorCore(GraphEvaluatorConfig(cmi_ema=0.999), _manipulation_spec())
    core.evaluated_updates = 1_000
    assert abs(core.previous_weight(1_100) - 0.999 ** 100) < 1e-12  # 100 updates on: ~0.905
    assert core.previous_weight(1_000) == 0.999  # a newer version without updates: barely moved
    assert core.previous_weight(400) == 0.0  # fewer updates: a new model, so the average starts over


def test_evaluations_average_cmi_by_updates_and_resume(tmp_path) -> None:
    import torch

    from causal.cdl import CDLConfig, CDLModel, model_config_json
    from causal.method import export_tensors
    from causal.factored import FactorLayout

    spec = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3)).spec
    cfg = GraphEvaluatorConfig(min_heldout=64, eval_samples=64, cmi_ema=0.99)
    core = GraphEvaluatorCore(cfg, spec)
    rng = np.random.default_rng(0)
    batch_rows = 64
    state = rng.integers(0, 5, (batch_rows, spec.state_dim)).astype(np.float32)
    core.heldout.add(state, rng.integers(0, 15, (batch_rows, 1)).astype(np.float32), state)
    layout = FactorLayout.from_spec(spec)
    estimates = []
    torch.manual_seed(0)
    for version, updates in ((1, 100), (2, 150)):
        model = CDLModel(layout, CDLConfig())
        core.load_weights(Weights(model="cdl", version=version, config_json=model_config_json(layout, CDLConfig()),
                                  env_steps=10, updates=updates, tensors=export_tensors(model)))
        before = None if core.cmi_ema is None else core.cmi_ema.copy()
        core.evaluate()
        held = (core.heldout.state, core.heldout.action, core.heldout.next_state)
        fresh = core.model.cmi(*(torch.from_numpy(x[:batch_rows]) for x in held)).numpy()  # all of it
        estimates.append((before, fresh, core.cmi_ema.copy()))
    before, fresh, after = estimates[1]
    weight = 0.99 ** 50
    # An untrained model's CMI reaches ~1e5 nats, and the evaluator sums the same rows in another order:
    # float32 rounding is relative to the magnitude, so is the tolerance.
    expected = weight * before + (1 - weight) * fresh
    np.testing.assert_allclose(after, expected, rtol=1e-4, atol=1e-6 * max(1.0, float(np.abs(expected).max())))
    first = estimates[0][1]  # the first estimate is taken as is
    np.testing.assert_allclose(estimates[0][2], first, rtol=1e-4, atol=1e-6 * max(1.0, float(np.abs(first).max())))
    core.checkpoint(tmp_path / "ev.pt")
    again = GraphEvaluatorCore(cfg, spec)
    assert again.restore(tmp_path / "ev.pt")
    assert (again.evaluated_version, again.evaluated_updates) == (2, 150)
    assert np.array_equal(again.cmi_ema, core.cmi_ema)


def test_evaluator_config_rejects_a_moving_average_that_never_moves() -> None:
    import pytest

    with pytest.raises(ValueError, match="cmi_ema"):
        GraphEvaluatorConfig(cmi_ema=1.0)
