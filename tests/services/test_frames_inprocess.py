"""A run with frames, in one process (the fast twin of tests/integration/test_frames_pipeline.py): the
unchanged env-worker, factor-extractor, dynamics-learner and graph-evaluator over the in-memory bus, wired
by the supervisor's wiring with ``--worker-publish-frames true``. The learner trains CDL on the slot
transitions, unchanged: its weights are over the slot factors and the evaluator reports a graph over them."""
from __future__ import annotations

import json
import time

import pytest
import torch

from causal.methods import get_method, method_config
from envs import make_env
from proto import topics
from proto.codec import decode
from proto.messages import GraphReport, Weights
from services.runtime.config import build_config
from services.supervisor import inprocess
from services.supervisor.config import RunConfig
from services.supervisor.wiring import learning_services, resolve, service_configs
from tests.waiting import wait_for


def _cfg(tmp_path, **kw) -> RunConfig:
    settings = dict(env="chemical-pixels", graph="chain", num_objects=3, run_dir=str(tmp_path), run_id="frames-mem",
                    progress=False, worker_publish_frames=True, worker_batch_steps=64, worker_max_steps_per_second=500,
                    extractor_ae_updates=3, extractor_slot_updates=3, extractor_warmup_frames=64,
                    extractor_slot_batch_size=8, cdl_feature_hidden=16, cdl_feature_dim=16, cdl_predictor_hidden=16,
                    cdl_batch_size=32, learner_warmup_steps=64, learner_publish_every_s=0.5,
                    evaluator_min_interval_s=0.5, evaluator_min_heldout=32)
    return build_config(RunConfig, **{**settings, **kw})


def test_wiring_starts_an_extractor_with_frames_only(tmp_path) -> None:
    frames = resolve(_cfg(tmp_path))
    assert learning_services(frames)[:2] == ("factor-extractor", "dynamics-learner")
    configs = service_configs(frames, "memory")
    assert configs["env-worker"].publish_frames and not configs["env-worker"].local_graphs
    assert configs["factor-extractor"].slot_updates == 3 and configs["factor-extractor"].run_id == "frames-mem"
    plain = resolve(_cfg(tmp_path, worker_publish_frames=False))
    assert "factor-extractor" not in learning_services(plain)
    with pytest.raises(ValueError, match="renders no frames"):
        resolve(_cfg(tmp_path, env="chemical"))
    with pytest.raises(ValueError, match="method 'dyno' learns from frames itself"):
        resolve(_cfg(tmp_path, method="dyno"))
    with pytest.raises(ValueError, match="--extractor-num-slots must be 0 or 4"):
        resolve(_cfg(tmp_path, extractor_num_slots=6))
    assert resolve(_cfg(tmp_path, extractor_num_slots=6, extractor_identity="none")).extractor.num_slots == 6
    two_tone = service_configs(resolve(_cfg(tmp_path, env="chemical-pixels-two-tone")), "memory")["env-worker"]
    assert two_tone.env == "chemical-pixels-two-tone" and make_env(two_tone.env).two_tone


def test_dyno_on_the_two_tone_env_draws_two_part_objects_whatever_its_flag_says(tmp_path) -> None:
    """Dyn-O renders its own frames from the states, so the env's name is what sets ``two_tone``."""
    for env, flag, expected in (("chemical-pixels-two-tone", False, True), ("chemical-pixels", False, False),
                                ("chemical-pixels", True, True)):
        cfg = resolve(_cfg(tmp_path, method="dyno", env=env, worker_publish_frames=False, dyno_two_tone=flag))
        assert method_config(cfg.models, "dyno").two_tone is expected, env
    assert get_method("cdl").env_settings == {}


def test_cdl_learns_over_slots_from_frames_in_process(tmp_path) -> None:
    torch.set_num_threads(1)
    cfg = _cfg(tmp_path)
    stack = inprocess.InProcessStack(cfg, services=learning_services(resolve(cfg)))
    weights: list[Weights] = []
    reports: list[GraphReport] = []
    bus = stack.transport()
    bus.subscribe(topics.weights(stack.cfg.run_id, "cdl"), lambda k, p: weights.append(decode(p, Weights)))
    bus.subscribe(topics.graph(stack.cfg.run_id, "cdl"), lambda k, p: reports.append(decode(p, GraphReport)))
    stack.start()
    try:
        wait_for(lambda: reports, 240, "a graph report over slots")
    finally:
        stack.stop(timeout=120)
    names = ("background", "obj0", "obj1", "obj2")  # the identity head puts the slots in object order
    layout = json.loads(weights[-1].config_json)["layout"]
    assert tuple(layout["names"]) == names and layout["sizes"] == [16] * 4
    assert reports[-1].factor_names == names and reports[-1].cmi.shape == (4, 5)
    assert reports[-1].true_graph is not None and reports[-1].true_graph.shape == (4, 5)
    assert 0.0 <= reports[-1].metrics["f1"] <= 1.0  # scored against chain's object graph
    assert time.time() - reports[-1].timestamp < 600
