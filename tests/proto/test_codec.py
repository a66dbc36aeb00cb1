"""Codec contract: exact round trips, fuzzed input only ever raising ProtocolError."""
from __future__ import annotations

import json
from dataclasses import fields, replace
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from proto import REJECT_REASONS, SCHEMA_VERSION, Control, EnvSpec, GraphReport, LocalGraphReport, ProtocolError
from proto import ScoredBatch, ServiceStats, TransitionBatch, Weights, codec, decode, encode
from proto.messages import ACTION_KINDS, CONTROL_COMMANDS, FACTOR_KINDS, MESSAGE_TYPES

from tests.proto.samples import (
    SAMPLES, assert_same, control, env_spec, graph_report, raw_of,
    reason_of, scored, transitions, weights, wire,
)


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
        reward_parents=draw(st.none() | graphs(n + 1)),
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
        option=draw(st.none() | hnp.arrays(np.int32, t, elements=st.integers(-1, 6))),
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
        num_heldout=draw(counters), timestamp=draw(finite), **draw(reward_graphs(d)), **draw(edge_tests(d)),
    )


@st.composite
def edge_tests(draw: Any, d: int) -> dict[str, Any]:
    """A report's edge-test fields: the fixed rule without standard errors, or standard errors with
    undecided entries under either rule (schema version 5)."""
    if not draw(st.booleans()):
        return {}
    stderr = draw(hnp.arrays(np.float32, (d, d + 1), elements=st.floats(0, 1e3, width=32)))
    rule = draw(st.sampled_from(("fixed", "fdr")))
    return {"cmi_stderr": stderr, "undecided": draw(graphs(d, d + 1)), "edge_rule": rule,
            "fdr": draw(st.floats(0, 0.999)) if rule == "fdr" else 0.0, "min_cmi": draw(st.floats(0, 1))}


@st.composite
def reward_graphs(draw: Any, d: int) -> dict[str, Any]:
    """A report's reward graph fields: none, or scores with their parents (and maybe the truth)."""
    if not draw(st.booleans()):
        return {}
    return {"reward_scores": draw(finite_arrays(np.float32, d + 1)), "reward_parents": draw(graphs(d + 1)),
            "reward_threshold": draw(finite), "true_reward_parents": draw(st.none() | graphs(d + 1))}


@st.composite
def local_reports(draw: Any) -> LocalGraphReport:
    d, k = draw(st.integers(1, 4)), draw(st.integers(0, 3))
    return LocalGraphReport(
        draw(texts), draw(texts), draw(counters), draw(counters), draw(counters),
        factor_names=draw(fixed_lists(texts, d)), threshold=draw(finite),
        scores=draw(finite_arrays(np.float32, (k, d, d + 1))), truth=draw(graphs(k, d, d + 1)),
        metrics=draw(st.dictionaries(texts, finite, max_size=7)), num_transitions=draw(counters),
        timestamp=draw(finite),
    )


STRATEGIES: dict[type, st.SearchStrategy[Any]] = {
    EnvSpec: env_specs(), TransitionBatch: transition_batches(), ScoredBatch: scored_batches(),
    Weights: weight_snapshots(), GraphReport: graph_reports(), LocalGraphReport: local_reports(),
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
