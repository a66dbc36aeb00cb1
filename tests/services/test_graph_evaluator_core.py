"""graph-evaluator core: its reports carry the paper's scores and the identifiable ones."""
from __future__ import annotations

import numpy as np

from envs.manipulation_layout import CONSTANT_FACTORS, FACTOR_NAMES, FACTOR_OBJECTS
from envs.manipulation_truth import global_graph
from proto.messages import EnvSpec, Weights
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
    core.cmi_ema = cmi.astype(np.float32)
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
    spec = EnvWorkerCore(EnvWorkerConfig(graph="chain", num_objects=3)).spec
    assert constant_factor_indices(spec) == ()
    rng = np.random.default_rng(0)
    m = _report_metrics(spec, rng.uniform(0, 0.05, spec.global_graph.shape))
    paper = {k: v for k, v in m.items() if not k.startswith(("identifiable_", "unidentifiable_", "with_self_"))}
    assert {k: m[f"identifiable_{k}"] for k in paper} == paper and m["unidentifiable_true_edges"] == 0.0
