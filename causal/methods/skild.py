"""SkiLD (dissertation ch. 6) as a Causeway method: the dynamics model whose point-wise CMI gives the
induced local graphs (pCMI >= 0.02, the chapter's estimator), with SkiLD's skill settings.

What the services run for ``--method skild``: the dynamics-learner trains CDL's factored model
(at CDL's default settings; weights named ``skild``), and the graph-evaluator scores its local graphs
(pCMI) live against the household tasks' true local graphs and sends the induced graphs of every
batch (``InducedGraphs``). SkiLD has no global graph (chapter 6 defines only local ones), so runs
show local-graph reports and no graph report, as ELDEN's.

The skill discovery itself (graph history, graph selector, skill policies, eqs. 6.1-6.2;
:mod:`causal.skild`, :mod:`causal.skild_agent`) runs in the policy-learner's SkiLD mode, then a task
policy over the frozen skills; the env-workers act with them (:mod:`causal.skild_policy`; see
docs/methods/skild.md, "What runs where"). The benchmarks run the same cores in one process.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from causal.cdl import CDLConfig, CDLModel
from causal.cdl_trainer import CDLTrainer
from causal.factored import FactorLayout
from causal.method import Method, layout_from_config, model_config_json
from causal.methods.cdl import PointwiseCMI
from causal.skild import SkiLDConfig


class SkiLDTrainer:
    """CDL's trainer under SkiLD's name: the weights' config says ``skild`` (so an evaluator of this
    method accepts them) and carries SkiLD's settings; the model is CDL's at its default settings."""

    def __init__(self, layout: FactorLayout, cfg: SkiLDConfig, seed: int = 0) -> None:
        self.inner = CDLTrainer(layout, CDLConfig(), seed=seed)
        self.layout, self.cfg = layout, cfg

    def __getattr__(self, name: str) -> Any:
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        return self.inner.update(state, action, next_state)

    def set_parents(self, adjacency: np.ndarray) -> None:
        self.inner.set_parents(adjacency)

    def config_json(self) -> str:
        return model_config_json("skild", self.layout, self.cfg)

    def state_dict(self) -> dict[str, Any]:
        return self.inner.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.inner.load_state_dict(state)


def model_from_config(data: dict) -> CDLModel:
    """The induced-graph model (CDL's, default settings) of a ``skild`` model configuration."""
    if data.get("model") != "skild":
        raise ValueError(f"not a SkiLD model config: {data.get('model')!r}")
    return CDLModel(layout_from_config(data), CDLConfig())


METHOD = Method(
    name="skild",
    title="SkiLD (ch. 6): skills that induce local dependencies; induced graphs by point-wise CMI",
    config=SkiLDConfig,
    trainer=lambda layout, cfg, seed: SkiLDTrainer(layout, cfg, seed=seed),
    model_from_config=model_from_config,
    global_graph=None,
    local_graph=PointwiseCMI(),
)
