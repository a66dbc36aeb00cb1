"""The CMI-estimation comparison: a run's checkpointed model scored under each estimation choice."""
from __future__ import annotations

import json

import numpy as np
import torch

from benchmarks.cmi_estimation import main
from benchmarks.manipulation_offline import shard_path
from causal.cdl import CDLConfig, CDLModel, model_config_json
from causal.factored import FactorLayout
from envs.manipulation_layout import CONSTANT_FACTORS, FACTOR_NAMES, NUM_FACTORS
from services.runtime.checkpoint import save_checkpoint

LAYOUT = FactorLayout(names=FACTOR_NAMES, kinds=("continuous",) * NUM_FACTORS, sizes=(1,) * NUM_FACTORS,
                      locs=(0.0,) * NUM_FACTORS, scales=(0.1,) * NUM_FACTORS, action_kind="continuous",
                      action_size=4)


def test_every_choice_is_scored_and_the_exact_search_never_loses(tmp_path) -> None:
    torch.manual_seed(0)
    cfg = CDLConfig(feature_hidden=8, feature_dim=8, predictor_hidden=8)
    model = CDLModel(LAYOUT, cfg)
    fingerprint = json.dumps({"env": "manipulation", "model": json.loads(model_config_json(LAYOUT, cfg))})
    save_checkpoint({"fingerprint": fingerprint, "trainer": {"model": model.state_dict()}},
                    tmp_path / "checkpoints" / "dynamics-learner-0.pt")
    rng = np.random.default_rng(0)
    n = 120
    state = rng.normal(size=(n, NUM_FACTORS)).astype(np.float32) * 0.1
    state[:, [FACTOR_NAMES.index(name) for name in CONSTANT_FACTORS]] = 0.83  # on the table, as in the scene
    next_state = state + rng.normal(size=state.shape).astype(np.float32) * 0.01
    cache = tmp_path / "data"
    cache.mkdir()
    np.savez(shard_path(cache, n, 4), state=state, action=rng.uniform(-1, 1, (n, 4)).astype(np.float32),
             next_state=next_state)
    out = tmp_path / "estimation.json"
    main(["--run-dir", str(tmp_path), "--heldout", f"{n}:4", "--samples", "30", "--repeats", "3",
          "--cache", str(cache), "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    choices = {(r["samples"], r["constant_inputs"], r["search"]): r for r in rows}
    assert set(choices) == {(s, c, m) for s in ("all", 30) for c in ("zero", "raw") for m in ("exact", "grid")}
    assert all(r["draws"] == (1 if r["samples"] == "all" else 3) for r in rows)
    for s, c, _ in choices:  # the same matrices under both searches: exact is the maximum
        assert choices[(s, c, "exact")]["f1"]["mean"] >= choices[(s, c, "grid")]["f1"]["mean"] - 1e-12
    # a random model's CMI on the constant columns is not 0: zeroing them changes the scores
    assert choices[("all", "zero", "exact")]["roc_auc"] != choices[("all", "raw", "exact")]["roc_auc"]
