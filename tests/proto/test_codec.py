"""Codec contract: exact round trips, and every off-contract payload rejected with its reason."""
from __future__ import annotations

import ast
import json
from collections.abc import Callable
from dataclasses import fields, is_dataclass, replace
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from proto import REJECT_REASONS, SCHEMA_VERSION, Control, EnvSpec, GraphReport, ProtocolError
from proto import ScoredBatch, ServiceStats, TransitionBatch, Weights, codec, decode, encode
from proto.messages import ACTION_KINDS, CONTROL_COMMANDS, FACTOR_KINDS, MESSAGE_TYPES

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
    )


def env_spec() -> EnvSpec:
    return EnvSpec(
        env_id="chemical-v0", factor_names=("pos", "vel", "door"),
        factor_kinds=("continuous", "continuous", "categorical"), factor_sizes=(2, 2, 3),
        factor_objects=("agent", "agent", "door"),
        factor_locs=(0.0, 0.5, 0.0), factor_scales=(1.0, 2.0, 1.0),
        action_kind="categorical", action_size=4, episode_length=100,
        global_graph=np.eye(3, 4, dtype=np.uint8), config_json='{"seed": 0}',
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
    )


def control() -> Control:
    return Control("set_task", "lift", 12.5)


def stats() -> ServiceStats:
    return ServiceStats("dynamics-learner", "0", {"loss": 0.1, "steps_per_second": 120.0}, 1.7e9)


SAMPLES: dict[type, Callable[[], Any]] = {
    EnvSpec: env_spec, TransitionBatch: transitions, ScoredBatch: scored, Weights: weights,
    GraphReport: graph_report, Control: control, ServiceStats: stats,
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


# ----------------------------------------------------------------------------- round trips

names = st.from_regex(r"[A-Za-z0-9_.\-]{1,12}", fullmatch=True)
texts = st.text(max_size=12)
finite = st.floats(allow_nan=False, allow_infinity=False)
counters = st.integers(0, 2**62)


def finite_arrays(dtype: Any, shape: Any) -> st.SearchStrategy[np.ndarray]:
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        elements = st.floats(width=8 * dtype.itemsize, allow_nan=False, allow_infinity=False)
        return hnp.arrays(dtype, shape, elements=elements)
    return hnp.arrays(dtype, shape)


def graphs(*shape: int) -> st.SearchStrategy[np.ndarray]:
    return hnp.arrays(np.uint8, shape, elements=st.integers(0, 1))


def fixed_lists(strategy: st.SearchStrategy[Any], n: int, **kw: Any) -> st.SearchStrategy[tuple]:
    return st.lists(strategy, min_size=n, max_size=n, **kw).map(tuple)


@st.composite
def env_specs(draw: Any) -> EnvSpec:
    n = draw(st.integers(1, 5))
    kinds = draw(fixed_lists(st.sampled_from(FACTOR_KINDS), n))
    return EnvSpec(
        env_id=draw(texts), factor_names=draw(fixed_lists(names, n, unique=True)),
        factor_kinds=kinds,
        factor_sizes=tuple(draw(st.integers(2 if k == "categorical" else 1, 9)) for k in kinds),
        factor_objects=draw(fixed_lists(texts, n)), factor_locs=draw(fixed_lists(finite, n)),
        factor_scales=draw(fixed_lists(st.floats(1e-6, 1e6), n)),
        action_kind=draw(st.sampled_from(ACTION_KINDS)), action_size=draw(st.integers(1, 8)),
        episode_length=draw(st.integers(1, 10**6)),
        global_graph=draw(st.none() | graphs(n, n + 1)),
        config_json=json.dumps(draw(st.dictionaries(texts, st.integers()))),
    )


@st.composite
def transition_batches(draw: Any) -> TransitionBatch:
    t, s, a, d = (draw(st.integers(low, high)) for low, high in ((1, 12), (0, 5), (1, 3), (0, 4)))
    state, action, reward, next_state = (
        draw(finite_arrays(np.float32, shape)) for shape in ((t, s), (t, a), t, (t, s))
    )
    return TransitionBatch(
        worker_id=draw(names), seq=draw(counters), policy_version=draw(counters),
        state=state, action=action, reward=reward, next_state=next_state,
        terminated=draw(hnp.arrays(bool, t)), truncated=draw(hnp.arrays(bool, t)),
        episode_id=draw(hnp.arrays(np.int64, t)), step=draw(hnp.arrays(np.int32, t)),
        local_graph=draw(st.none() | graphs(t, d, d + 1)),
    )


@st.composite
def scored_batches(draw: Any) -> ScoredBatch:
    batch = draw(transition_batches())
    intrinsic = draw(finite_arrays(np.float32, len(batch)))
    return ScoredBatch(batch, intrinsic, draw(texts), draw(counters))


tensors = st.sampled_from(codec.ARRAY_DTYPES).flatmap(
    lambda dtype: finite_arrays(dtype, hnp.array_shapes(min_dims=0, max_dims=3, min_side=0))
)


@st.composite
def weight_snapshots(draw: Any) -> Weights:
    config = json.dumps(draw(st.dictionaries(texts, finite | st.integers() | texts, max_size=4)))
    named = draw(st.dictionaries(names, tensors, max_size=4))
    return Weights(draw(texts), draw(counters), config, named, draw(counters), draw(counters))


@st.composite
def graph_reports(draw: Any) -> GraphReport:
    d = draw(st.integers(1, 5))
    label = draw(fixed_lists(st.integers(0, 3), d))
    classes = (tuple(i for i in range(d) if label[i] == c) for c in range(3))
    return GraphReport(
        draw(texts), draw(counters), draw(counters), draw(counters),
        factor_names=draw(fixed_lists(texts, d)),
        cmi=draw(finite_arrays(np.float32, (d, d + 1))), adjacency=draw(graphs(d, d + 1)),
        threshold=draw(finite), controllable=next(classes), action_relevant=next(classes),
        action_irrelevant=next(classes), metrics=draw(st.dictionaries(texts, finite, max_size=7)),
        true_graph=draw(st.none() | graphs(d, d + 1)),
        num_heldout=draw(counters), timestamp=draw(finite),
    )


STRATEGIES: dict[type, st.SearchStrategy[Any]] = {
    EnvSpec: env_specs(), TransitionBatch: transition_batches(), ScoredBatch: scored_batches(),
    Weights: weight_snapshots(), GraphReport: graph_reports(),
    Control: st.builds(Control, st.sampled_from(CONTROL_COMMANDS), texts, finite),
    ServiceStats: st.builds(ServiceStats, names, names, st.dictionaries(texts, finite), finite),
}
messages = st.one_of(*STRATEGIES.values())


@pytest.mark.parametrize("cls", list(STRATEGIES), ids=lambda cls: cls.TYPE)
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_round_trip_is_exact(cls: type, data: st.DataObject) -> None:
    msg = data.draw(STRATEGIES[cls])
    assert_same(msg, decode(encode(msg), cls))


@pytest.mark.parametrize("cls", list(SAMPLES), ids=lambda cls: cls.TYPE)
def test_schema_covers_exactly_the_dataclass_fields(cls: type) -> None:
    assert list(codec._SCHEMAS[cls]) == [f.name for f in fields(cls)]
    assert cls in codec._VALIDATORS and MESSAGE_TYPES[cls.TYPE] is cls


def test_decoded_arrays_are_writeable_native_copies() -> None:
    payload = encode(weights())
    for array in decode(payload, Weights).tensors.values():
        assert array.flags.writeable and array.flags.c_contiguous and array.dtype.isnative
        array[...] = 0
    assert_same(decode(payload), weights())


def test_wire_format_is_plain_msgpack() -> None:
    batch = transitions()
    raw = raw_of(batch)
    assert raw["type"] == "TransitionBatch" and raw["schema_version"] == SCHEMA_VERSION
    assert raw["state"] == wire(batch.state) and raw["terminated"]["dtype"] == "bool"
    assert raw_of(scored())["transitions"] == raw
    assert raw_of(env_spec())["factor_names"] == ["pos", "vel", "door"]


def test_big_endian_and_strided_arrays_travel_little_endian_c_order() -> None:
    state = np.arange(24, dtype=">f4").reshape(4, 6)[:, ::2]
    msg = replace(transitions(), state=state, next_state=state)
    assert raw_of(msg)["state"]["data"] == np.ascontiguousarray(state, "<f4").tobytes()
    back = decode(encode(msg), TransitionBatch)
    assert back.state.dtype == np.float32 and back.state.dtype.isnative
    np.testing.assert_array_equal(back.state, state)


def test_numpy_scalars_and_ints_become_python_numbers() -> None:
    msg = replace(graph_report(), threshold=np.float32(0.5), num_heldout=np.int64(3))
    back = decode(encode(msg), GraphReport)
    assert (type(back.threshold), type(back.num_heldout)) == (float, int)
    raw = raw_of(control()) | {"issued_at": 3}
    assert type(decode(msgpack.packb(raw), Control).issued_at) is float


def test_encode_refuses_what_cannot_travel() -> None:
    for bad in (np.zeros(2, np.float16), np.array([object()])):
        with pytest.raises(TypeError):
            encode(replace(weights(), tensors={"x": bad}))
    with pytest.raises(TypeError):
        encode({"type": "Control"})  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        decode("not bytes")  # type: ignore[arg-type]


def test_decode_accepts_any_bytes_like() -> None:
    payload = encode(control())
    for data in (bytearray(payload), memoryview(payload)):
        assert decode(data, Control) == control()


def test_expected_filters_message_types() -> None:
    payload = encode(control())
    assert decode(payload, Control) == control()
    assert decode(payload, (EnvSpec, Control)) == control()
    assert reason_of(payload, EnvSpec) == "unexpected_type"
    assert reason_of(payload, (EnvSpec, Weights)) == "unexpected_type"


# --------------------------------------------------------------------------- fuzzed input

wire_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
    | st.text(max_size=8) | st.binary(max_size=16),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(texts, kids, max_size=4),
    max_leaves=12,
)


def decode_quietly(payload: bytes) -> None:
    """Decoding may succeed or fail, but fail only with a ProtocolError of a known reason."""
    try:
        decode(payload)
    except ProtocolError as err:
        assert err.reason in REJECT_REASONS


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_raise_only_protocol_error(data: bytes) -> None:
    decode_quietly(data)


@settings(max_examples=150, deadline=None)
@given(cls=st.sampled_from(list(SAMPLES)), data=st.data())
def test_random_field_values_raise_only_protocol_error(cls: type, data: st.DataObject) -> None:
    raw = {"type": cls.TYPE, "schema_version": SCHEMA_VERSION}
    raw |= {f.name: data.draw(wire_values) for f in fields(cls)}
    decode_quietly(msgpack.packb(raw))


@settings(max_examples=200, deadline=None)
@given(msg=messages, data=st.data())
def test_mutated_values_raise_only_protocol_error(msg: Any, data: st.DataObject) -> None:
    raw = raw_of(msg)
    node, key = raw, data.draw(st.sampled_from(sorted(raw)))
    while isinstance(node[key], dict) and node[key] and data.draw(st.booleans()):
        node, key = node[key], data.draw(st.sampled_from(sorted(node[key])))
    node[key] = data.draw(wire_values)
    decode_quietly(msgpack.packb(raw))


@pytest.mark.parametrize("cls", list(SAMPLES), ids=lambda cls: cls.TYPE)
def test_every_truncation_is_rejected(cls: type) -> None:
    payload = encode(SAMPLES[cls]())
    for cut in range(len(payload)):
        assert reason_of(payload[:cut]) == "malformed"


# ---------------------------------------------------------------- one reason per violation


DROP = object()


def put(path: str, value: Any) -> Mutation:
    """Set (or ``DROP``) one value of the raw map along a dotted path: ``factor_sizes.0``."""

    def mutate(raw: dict[str, Any]) -> None:
        node: Any = raw
        *parents, last = (int(p) if p.isdigit() else p for p in path.split("."))
        for part in parents:
            node = node[part]
        if value is DROP:
            del node[last]
        else:
            node[last] = value

    return mutate


def drop(path: str) -> Mutation:
    return put(path, DROP)


def nan_at(array: np.ndarray, value: float = np.nan) -> dict[str, Any]:
    bad = array.copy()
    bad.flat[-1] = value
    return wire(bad)


T = transitions()
SPEC = env_spec()
REPORT = graph_report()
F32_4, F32_5, I64_5 = np.zeros(4, np.float32), np.zeros(5, np.float32), np.zeros(5, np.int64)
FLOAT16 = {"dtype": "float16", "shape": [4, 3], "data": np.zeros((4, 3), np.float16).tobytes()}

CASES: dict[str, list[tuple[str, type, Mutation]]] = {
    "unknown_type": [
        ("no type", Control, drop("type")),
        ("unknown type", Control, put("type", "Nope")),
        ("type not str", Control, put("type", 3)),
        ("type unhashable", Control, put("type", ["Control"])),
    ],
    "bad_version": [
        ("version 2", Control, put("schema_version", 2)),
        ("no version", Control, drop("schema_version")),
        ("version bool", Control, put("schema_version", True)),
        ("version float", Control, put("schema_version", 1.0)),
        ("nested version", ScoredBatch, put("transitions.schema_version", 0)),
    ],
    "bad_field": [
        # field set and Python types
        ("missing field", Control, drop("argument")),
        ("extra field", Control, put("extra", 1)),
        ("bytes key", Control, lambda raw: raw.update({b"command": "stop"})),
        ("int as str", TransitionBatch, put("seq", "3")),
        ("int as bool", TransitionBatch, put("seq", True)),
        ("int as float", TransitionBatch, put("policy_version", 1.0)),
        ("str as int", TransitionBatch, put("worker_id", 5)),
        ("float as str", Control, put("issued_at", "now")),
        ("float as bool", Control, put("issued_at", True)),
        ("tuple as str", EnvSpec, put("factor_names", "ab")),
        ("tuple of floats for ints", EnvSpec, put("factor_sizes", [2.0, 2.0, 3.0])),
        ("tuple of str for floats", EnvSpec, put("factor_locs.0", "0")),
        ("array as list", TransitionBatch, put("state", [[0.0]])),
        ("required array nil", TransitionBatch, put("reward", None)),
        ("optional array as int", TransitionBatch, put("local_graph", 0)),
        ("map as list", GraphReport, put("metrics", [1.0])),
        ("map value str", GraphReport, put("metrics.f1", "x")),
        ("map bytes key", GraphReport, put("metrics", {b"f1": 1.0})),
        ("tensor not array", Weights, put("tensors.w", 1.0)),
        ("nested not map", ScoredBatch, put("transitions", 1)),
        ("nested wrong type", ScoredBatch, put("transitions.type", "EnvSpec")),
        ("nested missing field", ScoredBatch, drop("transitions.step")),
        # values outside their domain
        ("bad command", Control, put("command", "explode")),
        ("bad factor kind", EnvSpec, put("factor_kinds.0", "weird")),
        ("bad action kind", EnvSpec, put("action_kind", "weird")),
        ("categorical size 1", EnvSpec, put("factor_sizes.2", 1)),
        ("continuous size 0", EnvSpec, put("factor_sizes.0", 0)),
        ("zero scale", EnvSpec, put("factor_scales.1", 0.0)),
        ("no action", EnvSpec, put("action_size", 0)),
        ("zero episode", EnvSpec, put("episode_length", 0)),
        ("no factors", EnvSpec, put("factor_names", [])),
        ("duplicate factors", EnvSpec, put("factor_names", ["a", "a", "b"])),
        ("negative seq", TransitionBatch, put("seq", -1)),
        ("negative policy version", TransitionBatch, put("policy_version", -1)),
        ("worker id with slash", TransitionBatch, put("worker_id", "a/b")),
        ("worker id wildcard", TransitionBatch, put("worker_id", "*")),
        ("nested negative seq", ScoredBatch, put("transitions.seq", -1)),
        ("negative weights version", ScoredBatch, put("weights_version", -1)),
        ("negative version", Weights, put("version", -1)),
        ("config not json", Weights, put("config_json", "{oops")),
        ("config not object", Weights, put("config_json", "[1]")),
        ("config too deep", Weights, put("config_json", "[" * 100_000)),
        ("empty tensor name", Weights, put("tensors", {"": wire(np.zeros(2))})),
        ("index out of range", GraphReport, put("controllable", [3])),
        ("negative index", GraphReport, put("action_irrelevant", [-1])),
        ("empty service", ServiceStats, put("service", "")),
    ],
    "non_finite": [
        ("NaN state", TransitionBatch, put("state", nan_at(T.state))),
        ("inf reward", TransitionBatch, put("reward", nan_at(T.reward, np.inf))),
        ("NaN intrinsic", ScoredBatch, put("intrinsic_reward", nan_at(F32_4))),
        ("NaN tensor", Weights, put("tensors.b", nan_at(np.zeros(2)))),
        ("inf cmi", GraphReport, put("cmi", nan_at(REPORT.cmi, -np.inf))),
        ("NaN threshold", GraphReport, put("threshold", float("nan"))),
        ("inf metric", GraphReport, put("metrics.f1", float("inf"))),
        ("inf scale", EnvSpec, put("factor_scales.0", float("inf"))),
        ("NaN loc", EnvSpec, put("factor_locs.0", float("nan"))),
        ("NaN stat", ServiceStats, put("values.loss", float("nan"))),
        ("inf timestamp", Control, put("issued_at", float("-inf"))),
    ],
    "bad_array": [
        ("dtype not allowed", TransitionBatch, put("state", FLOAT16)),
        ("dtype object", TransitionBatch, put("state.dtype", "object")),
        ("dtype not str", TransitionBatch, put("state.dtype", 7)),
        ("wrong dtype", TransitionBatch, put("state", wire(T.state.astype(np.float64)))),
        ("wrong tensor dtype", Weights, put("tensors.w.dtype", "complex64")),
        ("bytes short", TransitionBatch, put("state.data", wire(T.state)["data"][:-1])),
        ("data as str", TransitionBatch, put("state.data", "abc")),
        ("negative dim", TransitionBatch, put("state.shape", [-4, -3])),
        ("bool dim", TransitionBatch, put("reward.shape", [True])),
        ("shape not list", TransitionBatch, put("reward.shape", 4)),
        ("too many dims", Weights, put("tensors.u8.shape", [1] * 8 + [4])),
        ("wrong ndim", TransitionBatch, put("reward", wire(T.reward[:, None]))),
        ("array key missing", TransitionBatch, drop("state.data")),
        ("array key extra", TransitionBatch, put("state.order", "C")),
        ("bool byte 2", TransitionBatch, put("terminated.data", b"\x00\x02\x00\x01")),
        ("global graph 2", EnvSpec, put("global_graph", wire(2 * SPEC.global_graph))),
        ("local graph 2", TransitionBatch, put("local_graph", wire(T.local_graph + 1))),
        ("adjacency 2", GraphReport, put("adjacency", wire(2 * REPORT.adjacency))),
        ("true graph 2", GraphReport, put("true_graph", wire(2 * REPORT.adjacency))),
    ],
    "too_large": [
        ("declared shape oversize", TransitionBatch, put("state.shape", [2**25, 1])),
        ("tensor oversize", Weights, put("tensors.u8.shape", [2**24 + 1])),
        ("string > 1 MiB", Control, put("argument", "x" * (2**20 + 1))),
    ],
    "inconsistent": [
        ("next_state shape", TransitionBatch, put("next_state", wire(T.state[:, :2]))),
        ("action rows", TransitionBatch, put("action", wire(T.action[:3]))),
        ("reward length", TransitionBatch, put("reward", wire(T.reward[:3]))),
        ("episode_id length", TransitionBatch, put("episode_id", wire(I64_5))),
        ("local graph square", TransitionBatch, put("local_graph", wire(T.local_graph[..., :2]))),
        ("local graph rows", TransitionBatch, put("local_graph", wire(T.local_graph[:3]))),
        ("intrinsic length", ScoredBatch, put("intrinsic_reward", wire(F32_5))),
        ("sizes short", EnvSpec, put("factor_sizes", [2, 2])),
        ("scales long", EnvSpec, put("factor_scales", [1.0] * 4)),
        ("global graph square", EnvSpec, put("global_graph", wire(np.eye(3, dtype="u1")))),
        ("cmi shape", GraphReport, put("cmi", wire(np.zeros((3, 3), np.float32)))),
        ("adjacency shape", GraphReport, put("adjacency", wire(np.zeros((4, 5), "u1")))),
        ("true graph shape", GraphReport, put("true_graph", wire(np.zeros((2, 3), "u1")))),
        ("classes overlap", GraphReport, put("action_relevant", [0, 1])),
        ("class duplicates", GraphReport, put("controllable", [0, 0])),
    ],
}


@pytest.mark.parametrize(
    "cls, mutate, reason",
    [pytest.param(cls, mutate, reason, id=name) for reason, cases in CASES.items()
     for name, cls, mutate in cases],
)
def test_violation_is_rejected_with_its_reason(cls: type, mutate: Mutation, reason: str) -> None:
    raw = raw_of(SAMPLES[cls]())
    mutate(raw)
    assert reason_of(msgpack.packb(raw)) == reason


MALFORMED = {
    "empty": b"", "never-used byte": b"\xc1", "array": msgpack.packb([1, 2]),
    "string": msgpack.packb("Control"), "int key": msgpack.packb({1: "int key"}),
    "trailing garbage": encode(control()) + b"\x00", "bad utf-8": b"\xa3\xff\xfe\xfd",
}


@pytest.mark.parametrize("payload", MALFORMED.values(), ids=MALFORMED.keys())
def test_malformed_payload(payload: bytes) -> None:
    assert reason_of(payload) == "malformed"


@pytest.mark.parametrize(
    "msg",
    [transitions(t=0), transitions(t=codec.MAX_STEPS + 1, s=1, a=1, d=1)],
    ids=["empty batch", "T > 65536"],
)
def test_batch_length_bounds(msg: TransitionBatch) -> None:
    assert reason_of(encode(msg)) == ("bad_field" if len(msg) == 0 else "too_large")


def test_oversize_payload_is_rejected_before_unpacking(monkeypatch: pytest.MonkeyPatch) -> None:
    def never(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("unpacked an oversize payload")

    monkeypatch.setattr(codec.msgpack, "unpackb", never)
    assert reason_of(b"\x00" * (codec.MAX_MESSAGE_BYTES + 1)) == "too_large"


def test_every_reason_is_exercised() -> None:
    seen = CASES.keys() | {"malformed", "unexpected_type"}
    assert seen == set(REJECT_REASONS)


def test_protocol_error_shape() -> None:
    err = ProtocolError("bad_field", "Control.command: 'explode'")
    assert isinstance(err, ValueError) and err.reason == "bad_field"
    assert str(err) == "bad_field: Control.command: 'explode'"
    with pytest.raises(ValueError, match="unknown reject reason"):
        ProtocolError("whatever", "")


# ------------------------------------------------------------------------------ no pickle

PICKLERS = {"pickle", "_pickle", "cPickle", "dill", "cloudpickle", "marshal", "shelve", "joblib"}


@pytest.mark.parametrize("path", sorted(Path(codec.__file__).parent.glob("*.py")), ids=str)
def test_proto_never_uses_pickle(path: Path) -> None:
    source = path.read_text()
    imported: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            imported |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            imported.add(node.module.split(".")[0])
    assert not imported & PICKLERS
    assert "allow_pickle" not in source and "np.load" not in source
    assert not PICKLERS & set(vars(codec))
