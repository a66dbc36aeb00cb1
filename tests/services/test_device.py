"""``--device auto|cpu|cuda``: one run-wide setting, refused where it cannot hold, and a device path whose
weights and checkpoints stay device-independent. Runs on CPU (no GPU is needed: CUDA's absence is
simulated; tensors made on the wrong device are caught on torch's ``meta`` device)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

from causal.cdl import CDLConfig, CDLModel
from causal.factored import FactorLayout
from causal.intrinsic import dense_and_causal_nll
from causal.methods import get_method
from proto.messages import Weights
from services.cli import main as cli_main
from services.dynamics_learner.config import DynamicsLearnerConfig
from services.dynamics_learner.core import DynamicsLearnerCore
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.core import EnvWorkerCore
from services.graph_evaluator.config import GraphEvaluatorConfig
from services.graph_evaluator.core import GraphEvaluatorCore
from services.runtime.checkpoint import load_checkpoint
from services.runtime.config import build_config, parse_config
from services.runtime.device import resolve_device
from services.supervisor.config import RunConfig
from services.supervisor.wiring import service_configs

SMALL = dict(cdl_feature_hidden=8, cdl_feature_dim=8, cdl_predictor_hidden=8, cdl_batch_size=16, warmup_steps=100)
MODEL_SERVICES = ("dynamics-learner", "graph-evaluator", "intrinsic-reward", "policy-learner")


@pytest.fixture
def no_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_device_is_one_run_wide_flag_every_model_service_gets() -> None:
    assert RunConfig().device == "auto"
    cfg = parse_config(RunConfig, ["--device", "cpu"], {})
    assert {service_configs(cfg, "tcp/x:1")[name].device for name in MODEL_SERVICES} == {"cpu"}
    assert parse_config(RunConfig, [], {"CAUSEWAY_DEVICE": "cuda"}).device == "cuda"
    assert parse_config(DynamicsLearnerConfig, ["--device", "cuda"], {}).device == "cuda"


def test_an_unknown_device_is_refused_with_the_choices(capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        parse_config(RunConfig, ["--device", "tpu"], {}, prog="causeway run")
    assert exit_.value.code == 2
    assert "--device: invalid choice 'tpu' (choose from 'auto', 'cpu', 'cuda')" in capsys.readouterr().err


@pytest.mark.parametrize("name,supported,available,expected", [
    ("auto", ("cpu", "cuda"), False, "cpu"),
    ("auto", ("cpu", "cuda"), True, "cuda"),
    ("auto", ("cpu",), True, "cpu"),  # a method that runs on the CPU only stays there
    ("cpu", ("cpu", "cuda"), True, "cpu"),
    ("cuda", ("cpu", "cuda"), True, "cuda"),
])
def test_resolve_device(name: str, supported: tuple[str, ...], available: bool, expected: str) -> None:
    assert resolve_device(name, supported, lambda: available) == torch.device(expected)


def test_cuda_is_refused_where_it_cannot_run() -> None:
    with pytest.raises(ValueError, match="--device cuda: torch sees no CUDA device here"):
        resolve_device("cuda", ("cpu", "cuda"), lambda: False)
    with pytest.raises(ValueError, match="method runs on the CPU only"):
        resolve_device("cuda", ("cpu",), lambda: True)
    assert get_method("cdl").devices == ("cpu", "cuda")


def test_run_with_cuda_and_no_gpu_exits_2_before_anything_starts(tmp_path, capsys, no_cuda) -> None:
    run_dir = tmp_path / "r"
    code = cli_main(["run", "--device", "cuda", "--run-dir", str(run_dir), "--progress", "false"])
    assert code == 2
    assert "causeway run: error: --device cuda: torch sees no CUDA device here" in capsys.readouterr().err
    assert not run_dir.exists()


@pytest.mark.parametrize("module", ["services.dynamics_learner.service", "services.graph_evaluator.service",
                                    "services.intrinsic_reward.service", "services.policy_learner.service"])
def test_a_service_started_on_its_own_with_cuda_and_no_gpu_exits_78(module: str, monkeypatch, no_cuda) -> None:
    import importlib

    threads = torch.get_num_threads()
    monkeypatch.setattr(importlib.import_module(module), "run", lambda cfg: pytest.fail("the service started"))
    try:
        with pytest.raises(SystemExit) as exit_:
            importlib.import_module(module).main(["--device", "cuda"])
    finally:
        torch.set_num_threads(threads)
    assert exit_.value.code == 78


def _trained_learner(device: str) -> tuple[DynamicsLearnerCore, EnvWorkerCore]:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3, batch_steps=256))
    core = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **SMALL, device=device), worker.spec)
    core.ingest(worker.collect())
    for _ in range(30):
        core.train_step()
    return core, worker


def _tensors(value: object) -> list[torch.Tensor]:
    return [leaf for leaf in tree_flatten(value)[0] if isinstance(leaf, torch.Tensor)]


def test_a_checkpoint_of_the_device_path_loads_on_cpu_with_the_same_outputs(tmp_path) -> None:
    core, worker = _trained_learner("auto")
    core.checkpoint(tmp_path / "learner.pt")
    raw = torch.load(tmp_path / "learner.pt", weights_only=True)  # no map_location: as written
    assert {t.device.type for t in _tensors(raw)} == {"cpu"}
    resumed = DynamicsLearnerCore(build_config(DynamicsLearnerConfig, **SMALL, device="cpu"), worker.spec)
    assert resumed.restore(tmp_path / "learner.pt") and resumed.device == torch.device("cpu")
    s, a, n = resumed.replay.all()
    with torch.no_grad():
        for model in (core.trainer.model, resumed.trainer.model):
            assert model.head_w1.device.type == "cpu"
        torch.testing.assert_close(resumed.trainer.model.cmi(s, a, n), core.trainer.model.cmi(s, a, n), rtol=0, atol=0)
    assert load_checkpoint(tmp_path / "learner.pt")["trainer"]["updates"] == core.trainer.updates == 30


def test_published_weights_are_cpu_arrays_the_evaluator_scores_alike(tmp_path) -> None:
    core, worker = _trained_learner("auto")
    weights = core.weights()
    evaluator = GraphEvaluatorCore(build_config(GraphEvaluatorConfig, device="auto"), worker.spec)
    evaluator.load_weights(Weights(model=weights.model, version=weights.version, config_json=weights.config_json,
                                   tensors=weights.tensors, updates=weights.updates, env_steps=weights.env_steps))
    s, a, n = core.replay.all()
    scores = evaluator.method.global_graph.scores(evaluator.model, s.to(evaluator.device), a.to(evaluator.device),
                                                  n.to(evaluator.device))
    expected = core.trainer.model.cmi(s, a, n).numpy()
    assert scores.shape == expected.shape
    torch.testing.assert_close(torch.from_numpy(scores), torch.from_numpy(expected), rtol=1e-5, atol=1e-6)


class _OneDevice(TorchFunctionMode):
    """Fails any torch call that mixes tensors on ``meta`` (standing for the accelerator) with CPU
    tensors of more than one element: what would fail, or copy silently, on a GPU."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        tensors = _tensors((args, kwargs))
        if any(t.is_meta for t in tensors):
            stray = [tuple(t.shape) for t in tensors if not t.is_meta and t.numel() > 1]
            if stray:
                raise AssertionError(f"{getattr(func, '__name__', func)} mixes meta tensors with CPU tensors {stray}")
        return func(*args, **kwargs)


def test_cdl_keeps_every_tensor_it_makes_on_its_inputs_device() -> None:
    worker = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3, batch_steps=8))
    layout = FactorLayout.from_spec(worker.spec)
    model = CDLModel(layout, CDLConfig(feature_hidden=8, feature_dim=8, predictor_hidden=8)).to("meta")
    n = layout.num_factors
    s = torch.zeros(16, worker.spec.state_dim, device="meta")
    a = torch.zeros(16, worker.spec.action_dim, device="meta")
    parents = torch.ones(n, n + 1, dtype=torch.bool, device="meta")
    with _OneDevice():
        masked = model.masked_nll(s, a, s, parents)
        dense, causal = dense_and_causal_nll(model, np.ones((n, n + 1), dtype=bool), s, a, s)
    assert masked.shape == (n, 16)
    assert dense.is_meta and causal.is_meta
    # training_nll and drop_one_gain run the heads only on the rows whose aggregate changes, a
    # data-dependent selection (``nonzero``) that meta tensors cannot compute; up to that point they
    # are checked here, and their index tensors are made on the features' device (causal/cdl_max.py).
    with pytest.raises(NotImplementedError, match="nonzero"), _OneDevice():
        model.training_nll(s, a, s, parents, torch.Generator().manual_seed(0))
    with pytest.raises(AssertionError, match="mixes meta tensors with CPU tensors"), _OneDevice():
        model.drop_one_gain(s, a, torch.zeros(16, worker.spec.state_dim))


def test_final_graph_of_a_cuda_run_is_computed_on_the_cpu(tmp_path, capsys, no_cuda) -> None:
    """``causeway final-graph`` takes its own ``--device`` (default auto), not the one the run trained on."""
    from services.runtime.config import write_config

    core, worker = _trained_learner("cpu")
    evaluator = GraphEvaluatorCore(build_config(GraphEvaluatorConfig), worker.spec)
    for _ in range(4):
        evaluator.ingest(worker.collect())
    core.checkpoint(tmp_path / "checkpoints" / "dynamics-learner-0.pt")
    evaluator.checkpoint(tmp_path / "checkpoints" / "graph-evaluator-0.pt")
    model = {k: v for k, v in SMALL.items() if k.startswith("cdl_")}
    write_config(build_config(RunConfig, graph="chain", num_objects=3, device="cuda", **model), tmp_path / "config.json")
    (tmp_path / "summary.json").write_text("{}")
    assert cli_main(["final-graph", "--run-dir", str(tmp_path), "--device", "cuda"]) == 2
    assert "--device cuda: torch sees no CUDA device here" in capsys.readouterr().err
    assert cli_main(["final-graph", "--run-dir", str(tmp_path)]) == 0
    assert "final_graph" in json.loads((tmp_path / "summary.json").read_text())


def test_each_model_service_picks_the_device_its_model_can_use(monkeypatch) -> None:
    """With a GPU (simulated: nothing is moved before weights arrive), CDL's learner-side models take
    it; the intrinsic-reward's own ensemble and CPU-only methods stay on the CPU."""
    from services.intrinsic_reward.config import IntrinsicRewardConfig
    from services.intrinsic_reward.core import IntrinsicRewardCore

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    spec = EnvWorkerCore(build_config(EnvWorkerConfig, graph="chain", num_objects=3)).spec
    cuda = torch.device("cuda")
    assert GraphEvaluatorCore(build_config(GraphEvaluatorConfig, device="auto"), spec).device == cuda
    assert GraphEvaluatorCore(build_config(GraphEvaluatorConfig, device="cpu"), spec).device == torch.device("cpu")
    assert IntrinsicRewardCore(IntrinsicRewardConfig(device="cuda"), spec).device == cuda
    ensemble = IntrinsicRewardCore(IntrinsicRewardConfig(device="cuda", reward="disagreement"), spec)
    assert ensemble.device == torch.device("cpu")
    cbm = GraphEvaluatorCore(build_config(GraphEvaluatorConfig, method="cbm", device="auto"), spec)
    assert cbm.device == torch.device("cpu")


def test_policy_agents_move_every_tensor_they_learn_with() -> None:
    """``to(device)`` of PPO and SAC leaves nothing behind (checked on torch's meta device), and
    batches are moved to the agent's device by ``on_device``."""
    from causal.rl import ActionSpec, PPOAgent, SACAgent
    from causal.rl.base import ReplayBatch, on_device

    meta = torch.device("meta")
    ppo = PPOAgent(6, ActionSpec("continuous", 2, (-1.0, -1.0), (1.0, 1.0)))
    ppo.to(meta)
    assert {t.device.type for t in [*ppo.net.parameters(), *ppo.net.buffers()]} == {"meta"}
    sac = SACAgent(6, ActionSpec("continuous", 2, (-1.0, -1.0), (1.0, 1.0)))
    sac.to(meta)
    modules = (sac.actor, sac.critic, sac.target_critic)
    assert {t.device.type for m in modules for t in [*m.parameters(), *m.buffers()]} == {"meta"}
    assert sac.log_alpha.is_meta and sac.alpha_optimizer.param_groups[0]["params"][0] is sac.log_alpha
    batch = ReplayBatch(torch.zeros(4, 6), torch.zeros(4, 2), torch.zeros(4), torch.zeros(4, 6), torch.zeros(4))
    assert on_device(batch, torch.device("cpu")) is batch
    moved = on_device(batch, meta)
    assert all(getattr(moved, name).is_meta for name in ("obs", "actions", "rewards", "next_obs", "terminated"))
