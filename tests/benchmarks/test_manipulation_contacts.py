"""The manipulation contact diagnostics: a run's checkpointed model comes back as it was saved, and
the contact-step CMI is the model's CMI over exactly the steps touching each cube."""
from __future__ import annotations

import json

import numpy as np
import torch

from benchmarks.manipulation_contacts import ROWS, SOURCES, Collected, contact_cmi
from causal.cdl import CDLConfig, CDLModel, model_config_json
from causal.factored import FactorLayout
from envs.manipulation_layout import FACTOR_NAMES, NUM_FACTORS
from services.runtime.checkpoint import save_checkpoint
from services.supervisor.evaluation import load_model

LAYOUT = FactorLayout(names=FACTOR_NAMES, kinds=("continuous",) * NUM_FACTORS, sizes=(1,) * NUM_FACTORS,
                      locs=(0.0,) * NUM_FACTORS, scales=(0.1,) * NUM_FACTORS, action_kind="continuous",
                      action_size=4)
CFG = CDLConfig(feature_hidden=8, feature_dim=8, predictor_hidden=8)


def test_load_cdl_rebuilds_the_checkpointed_model(tmp_path) -> None:
    torch.manual_seed(0)
    model = CDLModel(LAYOUT, CFG)
    fingerprint = json.dumps({"env": "manipulation", "model": json.loads(model_config_json(LAYOUT, CFG))})
    save_checkpoint({"fingerprint": fingerprint, "trainer": {"model": model.state_dict()}},
                    tmp_path / "checkpoints" / "dynamics-learner-0.pt")
    loaded = load_model(tmp_path)
    for (name, a), (_, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        torch.testing.assert_close(a, b, msg=name)
    assert not loaded.training


def test_contact_cmi_is_the_cmi_over_the_touching_steps() -> None:
    torch.manual_seed(1)
    model = CDLModel(LAYOUT, CFG).eval()
    rng = np.random.default_rng(0)
    n = 40
    state = rng.normal(size=(n, NUM_FACTORS)).astype(np.float32) * 0.1
    action = rng.uniform(-1, 1, (n, 4)).astype(np.float32)
    next_state = state + rng.normal(size=state.shape).astype(np.float32) * 0.01
    touching = {"unm": np.arange(n) < 10, "rand": np.zeros(n, bool)}
    data = Collected(state, action, next_state, touching, np.zeros(n, bool))
    out = contact_cmi(model, data)
    tensors = [torch.from_numpy(x) for x in (state, action, next_state)]
    overall = model.cmi(*tensors).numpy()
    first_ten = model.cmi(*(t[:10] for t in tensors)).numpy()
    assert out["unm"] == (float(overall[np.ix_(ROWS, SOURCES["unm"])].max()),
                          float(first_ten[np.ix_(ROWS, SOURCES["unm"])].max()))
    assert out["rand"][1] == 0.0  # no step touches rand
    assert data.fractions() == {"unm": 0.25, "rand": 0.0, "holding mov": 0.0}


def _run_dir(tmp_path, collector: str, bias_option: int | None = None):
    import dataclasses

    from envs import make_env
    from services.policy_learner.core import PolicyLearnerCore
    from services.supervisor.config import RunConfig
    from services.supervisor.wiring import service_configs

    cfg = RunConfig(env="manipulation", collector=collector, intrinsic="preddiff" if collector == "ppo" else "none")
    tmp_path.mkdir(parents=True)
    (tmp_path / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    policy_cfg = service_configs(cfg, "")["policy-learner"]
    if collector == "ppo":
        core = PolicyLearnerCore(policy_cfg, make_env("manipulation").unwrapped.env_spec())
        last = [m for m in core.agent.net.actor.modules() if isinstance(m, torch.nn.Linear)][-1]
        with torch.no_grad():
            last.bias[bias_option] = 30.0
        core.checkpoint(tmp_path / "checkpoints" / "policy-learner-0.pt")
    return tmp_path


def test_the_runs_policy_over_skills_picks_the_skills(tmp_path) -> None:
    import pytest

    from benchmarks.manipulation_contacts import run_chooser
    from envs.skills import OPTION_NAMES

    unm = OPTION_NAMES.index("grasp:unm")
    chooser = run_chooser(_run_dir(tmp_path / "ppo", "ppo", unm))
    obs = np.random.default_rng(0).normal(size=(20, NUM_FACTORS)).astype(np.float32)
    assert {int(chooser(o)) for o in obs} == {unm}
    with pytest.raises(SystemExit, match="no checkpointed policy over skills"):
        run_chooser(_run_dir(tmp_path / "random", "random"))
