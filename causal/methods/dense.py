"""Chapter 3's dense dynamics baselines as Causeway methods: ``modular`` (one network per factor,
CDL's architecture with nothing masked; Ke et al. 2021) and ``monolithic`` (one MLP, the usual MBRL
model). They learn dynamics but no graph: a run with ``--method modular`` trains and publishes
weights, and the evaluator, dashboard and summary show that there is no graph to show.

The models live in :mod:`causal.baselines`; this module gives them settings, a trainer with
checkpoint state, and registry entries.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from causal.baselines import DenseDynamics, DenseDynamicsTrainer, ModularModel, MonolithicModel
from causal.cdl import CDLConfig
from causal.factored import FactorLayout
from causal.method import Method, layout_from_config, model_config_json
from proto.settings import doc


@dataclass(frozen=True)
class ModularConfig:
    """Modular baseline (ch. 3.3.2): per-factor networks over every input, trained by maximum likelihood."""

    feature_hidden: int = doc(32, "hidden width of each per-(output, input) feature network (as CDL's)")
    feature_dim: int = doc(32, "feature size (as CDL's)")
    predictor_hidden: int = doc(64, "hidden width of each per-output head (as CDL's)")
    lr: float = doc(3e-3, "Adam learning rate")
    batch_size: int = doc(64, "transitions per update")
    grad_clip: float = doc(10.0, "gradient norm clip")

    def __post_init__(self) -> None:
        _check_positive(self)

    def cdl(self) -> CDLConfig:
        return CDLConfig(feature_hidden=self.feature_hidden, feature_dim=self.feature_dim,
                         predictor_hidden=self.predictor_hidden, lr=self.lr, batch_size=self.batch_size,
                         grad_clip=self.grad_clip)


@dataclass(frozen=True)
class MonolithicConfig:
    """Monolithic baseline (ch. 3.3.2): one MLP from all factors and the action to every next factor."""

    width: int = doc(512, "hidden width of the MLP (ch. 3 matches CDL's parameter count; 512 is about that "
                          "for 10-object Chemical)")
    depth: int = doc(3, "hidden layers")
    lr: float = doc(3e-3, "Adam learning rate")
    batch_size: int = doc(64, "transitions per update")
    grad_clip: float = doc(10.0, "gradient norm clip")

    def __post_init__(self) -> None:
        _check_positive(self)

    def cdl(self) -> CDLConfig:
        return CDLConfig(lr=self.lr, batch_size=self.batch_size, grad_clip=self.grad_clip)


def _check_positive(cfg: Any) -> None:
    for name, value in vars(cfg).items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive finite number, got {value}")


def _modular(layout: FactorLayout, cfg: ModularConfig) -> ModularModel:
    return ModularModel(layout, cfg.cdl())


def _monolithic(layout: FactorLayout, cfg: MonolithicConfig) -> MonolithicModel:
    return MonolithicModel(layout, cfg.width, cfg.depth, cfg.cdl())


_BUILD = {"modular": (ModularConfig, _modular), "monolithic": (MonolithicConfig, _monolithic)}


class DenseTrainer:
    """Maximum likelihood for a dense baseline, with the dynamics-learner's trainer interface."""

    def __init__(self, name: str, layout: FactorLayout, cfg: ModularConfig | MonolithicConfig, seed: int) -> None:
        torch.manual_seed(seed)
        self.name, self.cfg = name, cfg
        self.model: DenseDynamics = _BUILD[name][1](layout, cfg)
        self.inner = DenseDynamicsTrainer(self.model, cfg.lr, seed)

    @property
    def updates(self) -> int:
        return self.inner.updates

    @property
    def batch_size(self) -> int:
        return self.cfg.batch_size

    @property
    def lr(self) -> float:
        return self.cfg.lr

    def update(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> dict[str, float]:
        return self.inner.update(state, action, next_state)

    def set_parents(self, adjacency: np.ndarray) -> None:
        """A dense model uses every input: there is nothing to take from a graph."""

    def config_json(self) -> str:
        return model_config_json(self.name, self.model.layout, self.cfg)

    def state_dict(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "optimizer": self.inner.optimizer.state_dict(),
                "updates": self.inner.updates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        state = copy.deepcopy(state)
        self.model.load_state_dict(state["model"])
        self.inner.optimizer.load_state_dict(state["optimizer"])
        self.inner.updates = int(state["updates"])


def _method(name: str, title: str) -> Method:
    config, build = _BUILD[name]
    return Method(
        name=name, title=title, config=config,
        trainer=lambda layout, cfg, seed: DenseTrainer(name, layout, cfg, seed),
        model_from_config=lambda data: build(layout_from_config(data), config(**data[name])))


MODULAR = _method("modular", "Modular dense baseline (ch. 3.3.2): per-factor networks, no graph")
MONOLITHIC = _method("monolithic", "Monolithic dense baseline (ch. 3.3.2): one MLP, no graph")
