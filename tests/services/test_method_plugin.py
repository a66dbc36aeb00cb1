"""Methods are plug-ins: a method defined outside the services runs through the unchanged stack by
its registry name, and a method without a graph publishes none."""
from __future__ import annotations

import json
import time
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from torch import nn

from causal.abstraction import cdl_abstraction
from causal.factored import FactorCodec, FactorLayout
from causal.method import Method, layout_from_config, model_config_json
from causal.methods import get_method, method_names, model_from_config_json, register, unregister
from proto import topics
from proto.codec import decode
from proto.messages import GraphReport, Weights
from proto.settings import doc
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.inprocess import InProcessStack
from services.supervisor.wiring import learning_services


@dataclass(frozen=True)
class ProbeConfig:
    """A deliberately small method: one linear map from every encoded input to every next factor."""

    lr: float = doc(1e-2, "Adam learning rate")
    batch_size: int = doc(32, "transitions per update")
    threshold: float = doc(0.05, "edge if the mean absolute weight of an input block is at least this")


class ProbeModel(nn.Module):
    def __init__(self, layout: FactorLayout, cfg: ProbeConfig) -> None:
        super().__init__()
        self.layout, self.cfg, self.codec = layout, cfg, FactorCodec(layout)
        self.inputs = layout.num_factors * layout.input_width + layout.action_width
        self.linear = nn.Linear(self.inputs, layout.num_factors * layout.input_width)

    def encode(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.codec.encode_state(state).flatten(1), self.codec.encode_action(action)], dim=1)

    def loss(self, state: torch.Tensor, action: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        target = self.codec.encode_state(next_state).flatten(1)
        return (self.linear(self.encode(state, action)) - target).square().mean()

    def edge_scores(self) -> np.ndarray:
        n, w = self.layout.num_factors, self.layout.input_width
        weight = self.linear.weight.detach().abs()
        blocks = weight[:, : n * w].reshape(n, w, n, w).mean(dim=(1, 3))
        action = weight[:, n * w:].reshape(n, w, -1).mean(dim=(1, 2))
        return torch.cat([blocks, action[:, None]], dim=1).numpy()


class ProbeTrainer:
    def __init__(self, layout: FactorLayout, cfg: ProbeConfig, seed: int) -> None:
        torch.manual_seed(seed)
        self.cfg, self.model = cfg, ProbeModel(layout, cfg)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.updates, self.batch_size, self.lr = 0, cfg.batch_size, cfg.lr
        self.parents_seen = 0

    def update(self, state, action, next_state) -> dict[str, float]:
        loss = self.model.loss(state, action, next_state)
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        return {"nll_full": float(loss.detach())}

    def set_parents(self, adjacency: np.ndarray) -> None:
        self.parents_seen += 1

    def config_json(self) -> str:
        return model_config_json("probe", self.model.layout, self.cfg)

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.updates = state["updates"]


class ProbeGraph:
    name = "weight"

    def scores(self, model: ProbeModel, state, action, next_state) -> np.ndarray:
        return model.edge_scores()

    def threshold(self, model: ProbeModel) -> float:
        return model.cfg.threshold


PROBE = Method(name="probe", title="a linear probe (test method)", config=ProbeConfig,
               trainer=lambda layout, cfg, seed: ProbeTrainer(layout, cfg, seed),
               model_from_config=lambda data: ProbeModel(layout_from_config(data), ProbeConfig(**data["probe"])),
               global_graph=ProbeGraph(), abstraction=cdl_abstraction)


@pytest.fixture
def probe():
    register(PROBE)
    yield PROBE
    unregister(PROBE.name)


def test_the_registry_knows_every_method_and_rebuilds_models_by_name(probe) -> None:
    assert {"cdl", "modular", "monolithic", "probe"} <= set(method_names())
    with pytest.raises(KeyError, match="unknown method 'nope'; known: ") as refused:
        get_method("nope")
    assert set(str(refused.value).split("known: ")[1].strip("\"'").split(", ")) == set(method_names())
    layout = FactorLayout(("a",), ("categorical",), (3,), (0.0,), (1.0,), "categorical", 2)
    text = ProbeTrainer(layout, ProbeConfig(), 0).config_json()
    assert isinstance(model_from_config_json(text), ProbeModel) and json.loads(text)["model"] == "probe"
    with pytest.raises(ValueError, match="names no method"):
        model_from_config_json("{}")


def _collect(stack: InProcessStack, key: str, kind: type) -> list:
    found: list = []
    stack.transport().subscribe(key, lambda _, payload: found.append(decode(payload, kind)))
    return found


def _stack(cfg: RunConfig) -> InProcessStack:
    overrides = {"dynamics-learner": {"warmup_steps": 200}, "graph-evaluator": {"min_heldout": 50}}
    return InProcessStack(cfg, config_overrides=overrides)


def test_a_method_registered_outside_the_services_runs_through_the_stack(probe, tmp_path) -> None:
    cfg = build_config(RunConfig, method="probe", graph="chain", num_objects=3, run_dir=str(tmp_path), run_id="pr",
                       learner_publish_every_s=0.3, evaluator_min_interval_s=0.3, worker_max_steps_per_second=3000,
                       progress=False)
    stack = _stack(cfg)
    weights = _collect(stack, topics.weights("pr", "probe"), Weights)
    reports = _collect(stack, topics.graph("pr", "probe"), GraphReport)
    stack.start()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(reports) < 3:
            time.sleep(0.2)
    finally:
        stack.stop()
    assert weights and all(w.model == "probe" for w in weights)
    assert len(reports) >= 3, "the evaluator published no graph of the registered method"
    last = reports[-1]
    assert last.kind == "probe" and last.threshold == ProbeConfig().threshold
    assert last.cmi.shape == (9, 10) and "f1" in last.metrics  # scored against Chemical's truth
    assert last.updates > 0 and last.controllable + last.action_relevant + last.action_irrelevant


def test_a_method_without_a_graph_trains_and_publishes_no_graph(tmp_path) -> None:
    cfg = build_config(RunConfig, method="modular", graph="chain", num_objects=3, run_dir=str(tmp_path),
                       run_id="mo", learner_publish_every_s=0.3, worker_max_steps_per_second=3000, progress=False,
                       modular_feature_hidden=8, modular_feature_dim=8, modular_predictor_hidden=8)
    assert learning_services(cfg) == ("dynamics-learner",)
    stack = _stack(cfg)
    weights = _collect(stack, topics.weights("mo", "modular"), Weights)
    reports = _collect(stack, topics.graph("mo"), GraphReport)
    stack.start()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (weights and weights[-1].updates > 20):
            time.sleep(0.2)
    finally:
        stack.stop()
    assert weights and weights[-1].updates > 20 and weights[-1].model == "modular"
    assert not reports
    model = model_from_config_json(weights[-1].config_json)
    assert type(model).__name__ == "ModularModel"


@pytest.mark.parametrize("flags,message", [
    (dict(method="modular", target_f1=0.9), "estimates no global graph"),
    (dict(method="modular", collector="ppo", intrinsic="preddiff"), "method 'modular' serves no such reward"),
    (dict(env="manipulation", task="match"), "poses no task 'match'"),
    (dict(graph="/nonexistent.json"), "graph file not found"),
    (dict(num_objects=0), "num_objects must be >= 1"),
])
def test_the_run_is_refused_before_anything_starts(flags: dict, message: str) -> None:
    from services.supervisor.wiring import resolve

    with pytest.raises(ValueError, match=message):
        resolve(build_config(RunConfig, router_port=7447, **flags))
