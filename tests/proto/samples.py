"""Fixed sample messages and wire helpers shared by the codec tests."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import fields, is_dataclass
from typing import Any

import msgpack
import numpy as np
import pytest

from proto import REJECT_REASONS, Control, EnvSpec, GraphReport, LocalGraphReport, ProtocolError
from proto import FrameBatch, ScoredBatch, ServiceStats, TransitionBatch, Weights, decode, encode
from proto.messages import LatentActions

Mutation = Callable[[dict[str, Any]], None]

# ------------------------------------------------------------------------------ fixed samples


def transitions(t: int = 4, s: int = 3, a: int = 2, d: int = 2) -> TransitionBatch:
    rng = np.random.default_rng(0)
    state, action, reward, next_state = (
        rng.normal(size=shape).astype(np.float32) for shape in ((t, s), (t, a), t, (t, s))
    )
    return TransitionBatch(
        worker_id="worker-0", seq=7, policy_version=3,
        state=state, action=action, reward=reward, next_state=next_state,
        terminated=np.arange(t) == t - 1, truncated=np.zeros(t, bool),
        episode_id=np.full(t, 11, np.int64), step=np.arange(t, dtype=np.int32),
        local_graph=rng.integers(0, 2, size=(t, d, d + 1), dtype=np.uint8),
        option=np.r_[2, -1, -1, 0][:t].astype(np.int32),
    )


def frame_batch(t: int = 4, size: int = 8) -> FrameBatch:
    """``t`` steps over ``t + 2`` frames: an episode ends after step 1 and the next starts from a reset frame."""
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 256, size=(t + 2, size, size, 3), dtype=np.uint8)
    state_frame = np.r_[0, 1, 3:t + 1].astype(np.int32)[:t]
    next_frame = np.r_[1, 2, 4:t + 2].astype(np.int32)[:t]
    return FrameBatch(
        worker_id="w0", seq=3, policy_version=0, frames=frames, state_frame=state_frame, next_frame=next_frame,
        action=rng.integers(0, 4, size=(t, 1)).astype(np.float32), reward=np.zeros(t, np.float32),
        terminated=np.zeros(t, bool), truncated=np.arange(t) == 1, episode_id=np.r_[0, 0, [1] * (t - 2)].astype(np.int64),
        step=np.r_[0, 1, range(t - 2)].astype(np.int32), labels=rng.integers(0, 3, size=(t + 2, size, size), dtype=np.uint8),
    )


def env_spec() -> EnvSpec:
    return EnvSpec(
        env_id="chemical-v0", factor_names=("pos", "vel", "door"),
        factor_kinds=("continuous", "continuous", "categorical"), factor_sizes=(2, 2, 3),
        factor_objects=("agent", "agent", "door"),
        factor_locs=(0.0, 0.5, 0.0), factor_scales=(1.0, 2.0, 1.0),
        action_kind="categorical", action_size=4, episode_length=100,
        global_graph=np.eye(3, 4, dtype=np.uint8), config_json='{"seed": 0}',
        reward_parents=np.array([1, 0, 0, 1], np.uint8),
    )


def scored() -> ScoredBatch:
    return ScoredBatch(transitions(), np.linspace(0, 1, 4, dtype=np.float32), "elden", 5)


def weights() -> Weights:
    tensors = {
        "w": np.arange(6, dtype=np.float32).reshape(3, 2), "b": np.array([0.5, -1.0]),
        "count": np.array(5, np.int64), "mask": np.eye(2, 3, dtype=bool),
        "ids": np.arange(4, dtype=np.int32), "u8": np.arange(4, dtype=np.uint8),
    }
    return Weights("dynamics", 3, '{"hidden": 64}', tensors, updates=10, env_steps=1000)


def graph_report() -> GraphReport:
    return GraphReport(
        kind="cdl", weights_version=3, env_steps=1000, updates=10,
        factor_names=("pos", "vel", "door"),
        cmi=np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4),
        adjacency=np.eye(3, 4, dtype=np.uint8), threshold=0.02,
        controllable=(0,), action_relevant=(1,), action_irrelevant=(2,),
        metrics={"f1": 1.0, "accuracy": 0.5}, true_graph=np.eye(3, 4, dtype=np.uint8),
        num_heldout=256, timestamp=1.7e9,
        reward_scores=np.array([0.5, 0.001, 0.0, 0.2], np.float32), reward_parents=np.array([1, 0, 0, 1], np.uint8),
        reward_threshold=0.01, true_reward_parents=np.array([1, 0, 1, 1], np.uint8),
        cmi_stderr=np.full((3, 4), 0.004, np.float32), undecided=np.eye(3, 4, 1, dtype=np.uint8),
        edge_rule="fdr", fdr=0.05, min_cmi=5e-4,
    )


def local_report() -> LocalGraphReport:
    rng = np.random.default_rng(1)
    return LocalGraphReport(
        kind="cdl", estimator="pcmi", weights_version=3, env_steps=1000, updates=10,
        factor_names=("pos", "vel", "door"), threshold=0.02,
        scores=rng.normal(size=(2, 3, 4)).astype(np.float32),
        truth=rng.integers(0, 2, size=(2, 3, 4), dtype=np.uint8),
        metrics={"roc_auc": 0.8, "pr_auc": 0.4, "best_f1": 0.5}, num_transitions=500, timestamp=1.7e9,
    )


def latent_actions(t: int = 4, k: int = 3, d: int = 2) -> LatentActions:
    rng = np.random.default_rng(2)
    return LatentActions("flam", "w0", 7, 3, np.arange(t, dtype=np.int64), np.arange(t, dtype=np.int32),
                         rng.normal(size=(t, k, d)).astype(np.float32), rng.normal(size=(t, k, d)).astype(np.float32))


def control() -> Control:
    return Control("set_task", "lift", 12.5)


def stats() -> ServiceStats:
    return ServiceStats("dynamics-learner", "0", {"loss": 0.1, "steps_per_second": 120.0}, 1.7e9)


SAMPLES: dict[type, Callable[[], Any]] = {
    EnvSpec: env_spec, TransitionBatch: transitions, FrameBatch: frame_batch, ScoredBatch: scored, Weights: weights,
    GraphReport: graph_report, LocalGraphReport: local_report, Control: control, ServiceStats: stats,
    LatentActions: latent_actions,
}


def assert_same(a: Any, b: Any) -> None:
    """Field-by-field equality; arrays must agree in dtype, shape and bytes."""
    assert type(a) is type(b), (type(a), type(b))
    if isinstance(a, np.ndarray):
        assert (a.dtype, a.shape) == (b.dtype, b.shape)
        assert a.tobytes() == b.tobytes()
    elif is_dataclass(a):
        for f in fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name))
    elif isinstance(a, (dict, tuple)):
        assert len(a) == len(b)
        pairs = [(a[k], b[k]) for k in a] if isinstance(a, dict) else zip(a, b)
        for x, y in pairs:
            assert_same(x, y)
    else:
        assert a == b


def wire(array: np.ndarray) -> dict[str, Any]:
    """The documented wire form of an array, written independently of the codec."""
    little = array.astype(array.dtype.newbyteorder("<"))
    return {"dtype": array.dtype.name, "shape": list(array.shape), "data": little.tobytes()}


def raw_of(msg: Any) -> dict[str, Any]:
    return msgpack.unpackb(encode(msg))


def reason_of(payload: bytes, expected: Any = None) -> str:
    with pytest.raises(ProtocolError) as err:
        decode(payload, expected)
    assert err.value.reason in REJECT_REASONS
    return err.value.reason
