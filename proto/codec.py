"""msgpack codec for ``proto.messages``, with validation of everything that comes off the wire.

Wire format: one msgpack map ``{"type", "schema_version", <every dataclass field>}``. A numpy array
travels as ``{"dtype": name, "shape": [ints], "data": C-order little-endian bytes}``, a tuple as a
list, ``Weights.tensors`` as a map of array maps, and ``ScoredBatch.transitions`` as a full nested
``TransitionBatch`` map (its own type and version are checked). No pickle anywhere.

``decode`` checks, in order: payload size, msgpack framing, ``type``, ``expected``,
``schema_version``, the field set, each field's Python type (arrays: dtype, ndim, size, bytes,
finiteness), then the message's cross-field rules. Any failure raises ``ProtocolError`` whose
``reason`` is one of ``REJECT_REASONS``, a bounded set used as the ``reason`` label of
``causeway_messages_rejected_total``. Decoded arrays are fresh, writeable, native-order copies.
``encode`` trusts its input (the receiver validates) but refuses dtypes that cannot travel.
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import fields
from typing import Any, Final, TypeVar, overload

import msgpack
import numpy as np

from proto.messages import ACTION_KINDS, CONTROL_COMMANDS, FACTOR_KINDS, MESSAGE_TYPES
from proto.messages import BIASES, EDGE_RULES, SCHEMA_VERSION, Control, EnvSpec, FrameBatch, GraphReport, LocalGraphReport
from proto.messages import ScoredBatch
from proto.messages import ServiceStats, TransitionBatch, Weights
from proto.messages import SKILL_PHASES, InducedGraphs, SkillBatch

Message = (EnvSpec | TransitionBatch | FrameBatch | ScoredBatch | Weights | GraphReport | LocalGraphReport
           | SkillBatch | InducedGraphs | Control | ServiceStats)
M = TypeVar("M")

# Bounds checked before (payload, strings, containers) or while (arrays) building objects.
MAX_MESSAGE_BYTES: Final = 64 * 2**20
MAX_ARRAY_ELEMENTS: Final = 16 * 2**20
MAX_STR_BYTES: Final = 2**20
MAX_CONTAINER_LEN: Final = 2**16
MAX_CONTAINERS: Final = 2**17 + 256
"""Maps and lists in one message, counted while unpacking: a payload of nested empty containers is
refused before it is built (a 64 MiB one would otherwise cost gigabytes of Python objects)."""
MAX_STEPS: Final = 65536
MAX_NDIM: Final = 8
MAX_LOCAL_EXAMPLES: Final = 64
"""Example transitions a LocalGraphReport may carry."""
ARRAY_DTYPES: Final = ("float32", "float64", "int32", "int64", "uint8", "bool")
REJECT_REASONS: Final = (
    "malformed", "unknown_type", "unexpected_type", "bad_version", "bad_field",
    "bad_array", "non_finite", "too_large", "inconsistent",
)

_HEADER_KEYS: Final = frozenset({"type", "schema_version"})
_ARRAY_KEYS: Final = frozenset({"dtype", "shape", "data"})
# Same alphabet as proto.topics, matched with fullmatch so a trailing newline is refused too.
_KEY_SEGMENT: Final = re.compile(r"[A-Za-z0-9_.\-]+")


class ProtocolError(ValueError):
    """A message was rejected; ``reason`` is one of ``REJECT_REASONS``, ``detail`` says where."""

    def __init__(self, reason: str, detail: str) -> None:
        if reason not in REJECT_REASONS:
            raise ValueError(f"unknown reject reason {reason!r}")
        super().__init__(reason, detail)
        self.reason = reason
        self.detail = detail

    def __str__(self) -> str:
        return f"{self.reason}: {self.detail}"


def _require(ok: bool, reason: str, detail: str) -> None:
    if not ok:
        raise ProtocolError(reason, detail)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


# ---------------------------------------------------------------------------------------- encode


def encode(msg: Message) -> bytes:
    """Serialise a message to msgpack bytes (see the module docstring for the wire format)."""
    if type(msg) not in _SCHEMAS:
        raise TypeError(f"not a protocol message: {type(msg).__name__}")
    return msgpack.packb(_message_map(msg), use_bin_type=True, default=_encode_value)


def _message_map(msg: Message) -> dict[str, Any]:
    body = {f.name: getattr(msg, f.name) for f in fields(msg)}
    return {"type": msg.TYPE, "schema_version": SCHEMA_VERSION, **body}


def _encode_value(value: Any) -> Any:
    """msgpack ``default`` hook: arrays, numpy scalars and nested messages."""
    if isinstance(value, np.ndarray):
        return _array_map(value)
    if isinstance(value, np.generic):
        return value.item()
    if type(value) in _SCHEMAS:
        return _message_map(value)
    raise TypeError(f"cannot encode {type(value).__name__}")


def _array_map(array: np.ndarray) -> dict[str, Any]:
    name = array.dtype.name
    if name not in ARRAY_DTYPES:
        raise TypeError(f"array dtype {name} cannot travel; use one of {ARRAY_DTYPES}")
    little = array.astype(array.dtype.newbyteorder("<"), copy=False)
    return {"dtype": name, "shape": list(array.shape), "data": little.tobytes(order="C")}


# ---------------------------------------------------------------------------------------- decode


@overload
def decode(data: bytes, expected: type[M]) -> M: ...


@overload
def decode(data: bytes, expected: tuple[type, ...] | None = None) -> Message: ...


def decode(data: bytes, expected: type | tuple[type, ...] | None = None) -> Any:
    """Parse and validate one message; raise ``ProtocolError`` for anything off-contract.

    ``expected`` (a message class or a tuple of them) rejects other types as ``unexpected_type``.
    """
    raw = _unpack(data)
    cls = _message_class(raw)
    if expected is not None:
        allowed = expected if isinstance(expected, tuple) else (expected,)
        _require(cls in allowed, "unexpected_type", f"got {cls.TYPE}")
    return _decode_message(cls, raw, cls.TYPE)


def _unpack(data: bytes) -> dict[Any, Any]:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"decode() takes bytes, not {type(data).__name__}")
    data = bytes(data)
    _require(len(data) <= MAX_MESSAGE_BYTES, "too_large", f"payload of {len(data)} bytes")
    first = data[0] if len(data) else -1
    _require(0x80 <= first <= 0x8F or first in (0xDE, 0xDF), "malformed", "top level is not a map")
    budget = _ContainerBudget(MAX_CONTAINERS)
    try:
        raw = msgpack.unpackb(
            data, raw=False, strict_map_key=True, max_str_len=MAX_STR_BYTES,
            max_bin_len=MAX_MESSAGE_BYTES, max_array_len=MAX_CONTAINER_LEN,
            max_map_len=MAX_CONTAINER_LEN, list_hook=budget, object_hook=budget,
        )
    except _TooManyContainers:
        raise ProtocolError("too_large", f"more than {MAX_CONTAINERS} maps and lists") from None
    except Exception as exc:  # untrusted bytes: whatever the parser raises, the input is bad
        reason = "too_large" if "exceeds max_" in str(exc) else "malformed"
        raise ProtocolError(reason, f"msgpack: {type(exc).__name__} {exc}") from None
    _require(isinstance(raw, dict), "malformed", f"top level is {type(raw).__name__}, not a map")
    return raw


class _TooManyContainers(Exception):
    pass


class _ContainerBudget:
    """msgpack hook: counts every map and list as it is built, and stops the parse past ``limit``."""

    def __init__(self, limit: int) -> None:
        self.left = limit

    def __call__(self, container: Any) -> Any:
        self.left -= 1
        if self.left < 0:
            raise _TooManyContainers
        return container


def _message_class(raw: dict[Any, Any]) -> type:
    tag = raw.get("type")
    _require(isinstance(tag, str) and tag in MESSAGE_TYPES, "unknown_type", f"type {_short(tag)}")
    return MESSAGE_TYPES[tag]


def _decode_message(cls: type, raw: dict[Any, Any], path: str) -> Any:
    version = raw.get("schema_version")
    ok = type(version) is int and version == SCHEMA_VERSION
    _require(ok, "bad_version", f"{path}: schema_version {_short(version)}, want {SCHEMA_VERSION}")
    schema = _SCHEMAS[cls]
    keys = raw.keys() - _HEADER_KEYS
    missing = sorted(schema.keys() - keys)
    _require(not missing, "bad_field", f"{path}: missing {missing}")
    extra = [_short(k) for k in keys - schema.keys()]
    _require(not extra, "bad_field", f"{path}: unknown fields {sorted(extra)[:5]}")
    msg = cls(**{name: field(raw[name], f"{path}.{name}") for name, field in schema.items()})
    _VALIDATORS[cls](msg)
    return msg


# ------------------------------------------------------------------------------ field decoders

Decoder = Callable[[Any, str], Any]


def _str(value: Any, path: str) -> str:
    _require(isinstance(value, str), "bad_field", f"{path}: {type(value).__name__}, want str")
    return value


def _int(value: Any, path: str) -> int:
    _require(type(value) is int, "bad_field", f"{path}: {type(value).__name__}, want int")
    return value


def _float(value: Any, path: str) -> float:
    ok = type(value) in (int, float)
    _require(ok, "bad_field", f"{path}: {type(value).__name__}, want float")
    _require(math.isfinite(value), "non_finite", f"{path}: {value}")
    return float(value)


def _tuple(item: Decoder) -> Decoder:
    def decode_tuple(value: Any, path: str) -> tuple[Any, ...]:
        _require(isinstance(value, list), "bad_field", f"{path}: {type(value).__name__}, want list")
        return tuple(item(v, f"{path}[{i}]") for i, v in enumerate(value))

    return decode_tuple


def _str_map(item: Decoder) -> Decoder:
    def decode_map(value: Any, path: str) -> dict[str, Any]:
        _require(isinstance(value, dict), "bad_field", f"{path}: {type(value).__name__}, want map")
        bad_keys = [_short(k) for k in value if not isinstance(k, str)]
        _require(not bad_keys, "bad_field", f"{path}: non-str keys {bad_keys[:5]}")
        return {k: item(v, f"{path}[{k[:40]!r}]") for k, v in value.items()}

    return decode_map


def _optional(inner: Decoder) -> Decoder:
    def decode_optional(value: Any, path: str) -> Any:
        return None if value is None else inner(value, path)

    return decode_optional


def _nested(cls: type) -> Decoder:
    def decode_nested(value: Any, path: str) -> Any:
        _require(isinstance(value, dict), "bad_field", f"{path}: {type(value).__name__}, want map")
        tag = value.get("type")
        _require(tag == cls.TYPE, "bad_field", f"{path}: type {_short(tag)}, want {cls.TYPE}")
        return _decode_message(cls, value, path)

    return decode_nested


def _array(*dtypes: str, ndim: int | None = None) -> Decoder:
    """An array field of one of ``dtypes`` (and ``ndim`` dimensions, when given)."""

    def decode_array(value: Any, path: str) -> np.ndarray:
        ok = isinstance(value, dict)
        _require(ok, "bad_field", f"{path}: {type(value).__name__}, want array")
        ok = value.keys() == _ARRAY_KEYS
        _require(ok, "bad_array", f"{path}: keys {list(map(_short, value))}")
        dtype, shape, data = value["dtype"], _shape(value["shape"], path), value["data"]
        _require(dtype in dtypes, "bad_array", f"{path}: dtype {_short(dtype)}, want {dtypes}")
        _require(ndim in (None, len(shape)), "bad_array", f"{path}: shape {shape}, want {ndim}-D")
        count = math.prod(shape)
        _require(count <= MAX_ARRAY_ELEMENTS, "too_large", f"{path}: {count} elements")
        size = count * np.dtype(dtype).itemsize
        ok = isinstance(data, bytes) and len(data) == size
        _require(ok, "bad_array", f"{path}: {type(data).__name__} data, want {size} bytes")
        return _array_from_bytes(dtype, shape, data, path)

    return decode_array


def _shape(value: Any, path: str) -> tuple[int, ...]:
    ok = isinstance(value, list) and len(value) <= MAX_NDIM
    ok = ok and all(type(n) is int and n >= 0 for n in value)
    _require(ok, "bad_array", f"{path}: shape {_short(value)}")
    _require(max(value, default=0) <= MAX_ARRAY_ELEMENTS, "too_large", f"{path}: shape {_short(value)}")
    return tuple(value)


def _array_from_bytes(dtype: str, shape: tuple[int, ...], data: bytes, path: str) -> np.ndarray:
    if dtype == "bool" and data:
        ok = int(np.frombuffer(data, np.uint8).max()) <= 1
        _require(ok, "bad_array", f"{path}: bool byte > 1")
    wire = np.frombuffer(data, dtype=np.dtype(dtype).newbyteorder("<"))
    array = wire.astype(dtype).reshape(shape)  # astype copies: writeable, native byte order
    if array.dtype.kind == "f":
        _require(bool(np.isfinite(array).all()), "non_finite", f"{path}: NaN or inf")
    return array


_F32_1D, _F32_2D = _array("float32", ndim=1), _array("float32", ndim=2)
_GRAPH = _array("uint8", ndim=2)
_PARENTS = _array("uint8", ndim=1)
_SCHEMAS: Final[dict[type, dict[str, Decoder]]] = {
    EnvSpec: {
        "env_id": _str, "factor_names": _tuple(_str), "factor_kinds": _tuple(_str),
        "factor_sizes": _tuple(_int), "factor_objects": _tuple(_str),
        "factor_locs": _tuple(_float), "factor_scales": _tuple(_float),
        "action_kind": _str, "action_size": _int, "episode_length": _int,
        "global_graph": _optional(_GRAPH), "config_json": _str, "reward_parents": _optional(_PARENTS),
        "state_low": _optional(_F32_1D), "state_high": _optional(_F32_1D),
    },
    TransitionBatch: {
        "worker_id": _str, "seq": _int, "policy_version": _int,
        "state": _F32_2D, "action": _F32_2D, "reward": _F32_1D, "next_state": _F32_2D,
        "terminated": _array("bool", ndim=1), "truncated": _array("bool", ndim=1),
        "episode_id": _array("int64", ndim=1), "step": _array("int32", ndim=1),
        "local_graph": _optional(_array("uint8", ndim=3)), "option": _optional(_array("int32", ndim=1)),
    },
    FrameBatch: {
        "worker_id": _str, "seq": _int, "policy_version": _int, "frames": _array("uint8", ndim=4),
        "state_frame": _array("int32", ndim=1), "next_frame": _array("int32", ndim=1), "action": _F32_2D,
        "reward": _F32_1D, "terminated": _array("bool", ndim=1), "truncated": _array("bool", ndim=1),
        "episode_id": _array("int64", ndim=1), "step": _array("int32", ndim=1),
        "labels": _optional(_array("uint8", ndim=3)),
    },
    ScoredBatch: {
        "transitions": _nested(TransitionBatch), "intrinsic_reward": _F32_1D,
        "reward_kind": _str, "weights_version": _int,
    },
    Weights: {
        "model": _str, "version": _int, "config_json": _str,
        "tensors": _str_map(_array(*ARRAY_DTYPES)), "updates": _int, "env_steps": _int,
    },
    GraphReport: {
        "kind": _str, "weights_version": _int, "env_steps": _int, "updates": _int,
        "factor_names": _tuple(_str), "cmi": _F32_2D, "adjacency": _GRAPH, "threshold": _float,
        "controllable": _tuple(_int), "action_relevant": _tuple(_int),
        "action_irrelevant": _tuple(_int), "metrics": _str_map(_float),
        "true_graph": _optional(_GRAPH), "num_heldout": _int, "timestamp": _float,
        "reward_scores": _optional(_F32_1D), "reward_parents": _optional(_PARENTS), "reward_threshold": _float,
        "true_reward_parents": _optional(_PARENTS), "cmi_stderr": _optional(_F32_2D),
        "undecided": _optional(_GRAPH), "edge_rule": _str, "fdr": _float, "min_cmi": _float,
        "bias": _str, "cmi_null": _optional(_F32_2D), "reward_stderr": _optional(_F32_1D),
        "reward_undecided": _optional(_PARENTS),
    },
    LocalGraphReport: {
        "kind": _str, "estimator": _str, "weights_version": _int, "env_steps": _int, "updates": _int,
        "factor_names": _tuple(_str), "threshold": _float, "scores": _array("float32", ndim=3),
        "truth": _array("uint8", ndim=3), "metrics": _str_map(_float), "num_transitions": _int,
        "timestamp": _float,
    },
    SkillBatch: {
        "transitions": _nested(TransitionBatch), "phase": _str, "slot": _array("int32", ndim=1),
        "b": _array("int32", ndim=1), "started": _array("bool", ndim=1),
    },
    InducedGraphs: {
        "kind": _str, "worker_id": _str, "seq": _int, "weights_version": _int, "graphs": _array("uint8", ndim=3),
    },
    Control: {"command": _str, "argument": _str, "issued_at": _float},
    ServiceStats: {
        "service": _str, "instance": _str, "values": _str_map(_float), "timestamp": _float,
    },
}


# ---------------------------------------------------------------------- semantic validators


def _check_counters(msg: Any, *names: str) -> None:
    for name in names:
        value = getattr(msg, name)
        _require(value >= 0, "bad_field", f"{msg.TYPE}.{name}: {value} < 0")


def _check_graph(graph: np.ndarray, shape: tuple[int, ...], path: str) -> None:
    _require(graph.shape == shape, "inconsistent", f"{path}: shape {graph.shape}, want {shape}")
    _require(bool((graph <= 1).all()), "bad_array", f"{path}: values outside {{0, 1}}")


def _check_env_spec(m: EnvSpec) -> None:
    n = len(m.factor_names)
    _require(n >= 1, "bad_field", "EnvSpec.factor_names: empty")
    _require(all(m.factor_names), "bad_field", "EnvSpec.factor_names: empty name")
    _require(len(set(m.factor_names)) == n, "bad_field", "EnvSpec.factor_names: duplicates")
    for name in ("factor_kinds", "factor_sizes", "factor_objects", "factor_locs", "factor_scales"):
        count = len(getattr(m, name))
        _require(count == n, "inconsistent", f"EnvSpec.{name}: {count} entries for {n} factors")
    for kind, size in zip(m.factor_kinds, m.factor_sizes):
        _require(kind in FACTOR_KINDS, "bad_field", f"EnvSpec.factor_kinds: {_short(kind)}")
        least = 2 if kind == "categorical" else 1
        _require(size >= least, "bad_field", f"EnvSpec.factor_sizes: {kind} of size {size}")
    _require(all(s > 0 for s in m.factor_scales), "bad_field", "EnvSpec.factor_scales: <= 0")
    ok = m.action_kind in ACTION_KINDS
    _require(ok, "bad_field", f"EnvSpec.action_kind: {_short(m.action_kind)}")
    _require(m.action_size >= 1, "bad_field", f"EnvSpec.action_size: {m.action_size}")
    _require(m.episode_length >= 1, "bad_field", f"EnvSpec.episode_length: {m.episode_length}")
    if m.global_graph is not None:
        _check_graph(m.global_graph, (n, n + 1), "EnvSpec.global_graph")
    if m.reward_parents is not None:
        _check_graph(m.reward_parents, (n + 1,), "EnvSpec.reward_parents")
    _check_bounds(m)


def _check_bounds(m: EnvSpec) -> None:
    _require((m.state_low is None) == (m.state_high is None), "inconsistent",
             "EnvSpec: state_low and state_high come together")
    if m.state_low is None:
        return
    for name in ("state_low", "state_high"):
        shape = getattr(m, name).shape
        _require(shape == (m.state_dim,), "inconsistent", f"EnvSpec.{name}: shape {shape}, state_dim {m.state_dim}")
    _require(bool((m.state_low <= m.state_high).all()), "inconsistent", "EnvSpec: state_low above state_high")


def _check_transitions(m: TransitionBatch) -> None:
    steps = m.state.shape[0]
    _require(steps >= 1, "bad_field", "TransitionBatch: empty batch")
    _require(steps <= MAX_STEPS, "too_large", f"TransitionBatch: {steps} steps > {MAX_STEPS}")
    same = m.next_state.shape == m.state.shape
    _require(same, "inconsistent", f"TransitionBatch.next_state: shape {m.next_state.shape}")
    ok = m.action.shape[0] == steps
    _require(ok, "inconsistent", f"TransitionBatch.action: shape {m.action.shape}")
    for name in ("reward", "terminated", "truncated", "episode_id", "step"):
        shape = getattr(m, name).shape
        _require(shape == (steps,), "inconsistent", f"TransitionBatch.{name}: shape {shape}")
    if m.local_graph is not None:
        d = m.local_graph.shape[1]
        _check_graph(m.local_graph, (steps, d, d + 1), "TransitionBatch.local_graph")
    if m.option is not None:
        _require(m.option.shape == (steps,), "inconsistent", f"TransitionBatch.option: shape {m.option.shape}")
        _require(bool((m.option >= -1).all()), "bad_array", "TransitionBatch.option: below -1")
    _check_counters(m, "seq", "policy_version")
    ok = _KEY_SEGMENT.fullmatch(m.worker_id) is not None
    _require(ok, "bad_field", f"TransitionBatch.worker_id: {_short(m.worker_id)}")


def _check_frames(m: FrameBatch) -> None:
    steps, count = m.state_frame.shape[0], m.frames.shape[0]
    _require(steps >= 1, "bad_field", "FrameBatch: empty batch")
    _require(steps <= MAX_STEPS, "too_large", f"FrameBatch: {steps} steps > {MAX_STEPS}")
    _require(1 <= count <= 2 * steps, "inconsistent", f"FrameBatch.frames: {count} frames for {steps} steps")
    ok = m.frames.shape[3] == 3 and min(m.frames.shape[1:3]) >= 1
    _require(ok, "inconsistent", f"FrameBatch.frames: shape {m.frames.shape}, want [F, H, W, 3]")
    for name in ("next_frame", "reward", "terminated", "truncated", "episode_id", "step"):
        shape = getattr(m, name).shape
        _require(shape == (steps,), "inconsistent", f"FrameBatch.{name}: shape {shape}")
    _require(m.action.shape[0] == steps, "inconsistent", f"FrameBatch.action: shape {m.action.shape}")
    for name in ("state_frame", "next_frame"):
        index = getattr(m, name)
        _require(bool(((index >= 0) & (index < count)).all()), "inconsistent", f"FrameBatch.{name}: outside [0, {count})")
    if m.labels is not None:
        ok = m.labels.shape == m.frames.shape[:3]
        _require(ok, "inconsistent", f"FrameBatch.labels: shape {m.labels.shape}, frames {m.frames.shape}")
    _check_counters(m, "seq", "policy_version")
    ok = _KEY_SEGMENT.fullmatch(m.worker_id) is not None
    _require(ok, "bad_field", f"FrameBatch.worker_id: {_short(m.worker_id)}")


def _check_scored(m: ScoredBatch) -> None:
    shape, want = m.intrinsic_reward.shape, (len(m.transitions),)
    _require(shape == want, "inconsistent", f"ScoredBatch.intrinsic_reward: {shape}, want {want}")
    _check_counters(m, "weights_version")


def _check_weights(m: Weights) -> None:
    _check_counters(m, "version", "updates", "env_steps")
    _require(all(m.tensors), "bad_field", "Weights.tensors: empty tensor name")
    try:
        config = json.loads(m.config_json)
    except (ValueError, RecursionError):
        raise ProtocolError("bad_field", "Weights.config_json: not JSON") from None
    _require(isinstance(config, dict), "bad_field", "Weights.config_json: not a JSON object")


def _check_graph_report(m: GraphReport) -> None:
    d = len(m.factor_names)
    shape = (d, d + 1)
    _require(m.cmi.shape == shape, "inconsistent", f"GraphReport.cmi: {m.cmi.shape}, want {shape}")
    _check_graph(m.adjacency, shape, "GraphReport.adjacency")
    if m.true_graph is not None:
        _check_graph(m.true_graph, shape, "GraphReport.true_graph")
    classes = m.controllable + m.action_relevant + m.action_irrelevant
    ok = all(0 <= i < d for i in classes)
    _require(ok, "bad_field", f"GraphReport: factor index outside [0, {d})")
    _require(len(set(classes)) == len(classes), "inconsistent", "GraphReport: classes overlap")
    _check_counters(m, "weights_version", "env_steps", "updates", "num_heldout")
    _check_reward_graph(m, d)
    _check_edge_tests(m, shape)


def _check_edge_tests(m: GraphReport, shape: tuple[int, int]) -> None:
    """Standard errors and undecided entries come together, shaped like the CMI; the rule is known."""
    ok = (m.cmi_stderr is None) == (m.undecided is None)
    _require(ok, "inconsistent", "GraphReport: cmi_stderr and undecided come together")
    if m.cmi_stderr is not None:
        got = m.cmi_stderr.shape
        _require(got == shape, "inconsistent", f"GraphReport.cmi_stderr: {got}, want {shape}")
        _require(bool((m.cmi_stderr >= 0).all()), "bad_array", "GraphReport.cmi_stderr: negative")
        _check_graph(m.undecided, shape, "GraphReport.undecided")
    _require(m.edge_rule in EDGE_RULES, "bad_field", f"GraphReport.edge_rule: {_short(m.edge_rule)}")
    ok = m.edge_rule == "fixed" or m.cmi_stderr is not None
    _require(ok, "inconsistent", "GraphReport: edge_rule fdr without cmi_stderr")
    _require(0.0 <= m.fdr < 1.0 and m.min_cmi >= 0.0, "bad_field", f"GraphReport: fdr {m.fdr}, min_cmi {m.min_cmi}")
    _require(m.bias in BIASES, "bad_field", f"GraphReport.bias: {_short(m.bias)}")
    ok = m.bias == "fixed" or (m.edge_rule == "fdr" and m.cmi_null is not None)
    _require(ok, "inconsistent", f"GraphReport: bias {m.bias} without the fdr rule and cmi_null")
    if m.cmi_null is not None:
        _require(m.cmi_null.shape == shape, "inconsistent", f"GraphReport.cmi_null: {m.cmi_null.shape}, want {shape}")


def _check_reward_graph(m: GraphReport, d: int) -> None:
    """Reward scores and parents come together, one entry per factor and the action."""
    ok = (m.reward_scores is None) == (m.reward_parents is None)
    _require(ok, "inconsistent", "GraphReport: reward_scores and reward_parents come together")
    if m.reward_scores is not None:
        shape = m.reward_scores.shape
        _require(shape == (d + 1,), "inconsistent", f"GraphReport.reward_scores: {shape}, want {(d + 1,)}")
        _check_graph(m.reward_parents, (d + 1,), "GraphReport.reward_parents")
    if m.true_reward_parents is not None:
        _check_graph(m.true_reward_parents, (d + 1,), "GraphReport.true_reward_parents")
    ok = (m.reward_stderr is None) == (m.reward_undecided is None) and (m.reward_stderr is None or m.reward_scores is not None)
    _require(ok, "inconsistent", "GraphReport: reward_stderr and reward_undecided come together, with reward_scores")
    if m.reward_stderr is not None:
        got = m.reward_stderr.shape
        _require(got == (d + 1,), "inconsistent", f"GraphReport.reward_stderr: {got}, want {(d + 1,)}")
        _require(bool((m.reward_stderr >= 0).all()), "bad_array", "GraphReport.reward_stderr: negative")
        _check_graph(m.reward_undecided, (d + 1,), "GraphReport.reward_undecided")


def _check_local_report(m: LocalGraphReport) -> None:
    d = len(m.factor_names)
    k = m.scores.shape[0]
    _require(k <= MAX_LOCAL_EXAMPLES, "too_large", f"LocalGraphReport: {k} examples > {MAX_LOCAL_EXAMPLES}")
    shape = (k, d, d + 1)
    _require(m.scores.shape == shape, "inconsistent", f"LocalGraphReport.scores: {m.scores.shape}, want {shape}")
    _check_graph(m.truth, shape, "LocalGraphReport.truth")
    _check_counters(m, "weights_version", "env_steps", "updates", "num_transitions")


def _check_skill_batch(m: SkillBatch) -> None:
    steps = (len(m.transitions),)
    for name in ("slot", "b", "started"):
        shape = getattr(m, name).shape
        _require(shape == steps, "inconsistent", f"SkillBatch.{name}: shape {shape}, want {steps}")
    _require(m.phase in SKILL_PHASES, "bad_field", f"SkillBatch.phase: {_short(m.phase)}")
    _require(bool((m.slot >= -1).all()), "bad_array", "SkillBatch.slot: below -1")
    _require(bool((m.b >= 0).all()), "bad_array", "SkillBatch.b: negative")


def _check_induced(m: InducedGraphs) -> None:
    t, d = m.graphs.shape[0], m.graphs.shape[1]
    _require(1 <= t <= MAX_STEPS, "bad_field", f"InducedGraphs: {t} steps")
    _check_graph(m.graphs, (t, d, d + 1), "InducedGraphs.graphs")
    _check_counters(m, "seq", "weights_version")
    for name in ("kind", "worker_id"):
        ok = _KEY_SEGMENT.fullmatch(getattr(m, name)) is not None
        _require(ok, "bad_field", f"InducedGraphs.{name}: {_short(getattr(m, name))}")


def _check_control(m: Control) -> None:
    _require(m.command in CONTROL_COMMANDS, "bad_field", f"Control.command: {_short(m.command)}")


def _check_stats(m: ServiceStats) -> None:
    _require(bool(m.service), "bad_field", "ServiceStats.service: empty")
    _require(bool(m.instance), "bad_field", "ServiceStats.instance: empty")


_VALIDATORS: Final[dict[type, Callable[[Any], None]]] = {
    EnvSpec: _check_env_spec,
    TransitionBatch: _check_transitions,
    FrameBatch: _check_frames,
    ScoredBatch: _check_scored,
    Weights: _check_weights,
    GraphReport: _check_graph_report,
    LocalGraphReport: _check_local_report,
    SkillBatch: _check_skill_batch,
    InducedGraphs: _check_induced,
    Control: _check_control,
    ServiceStats: _check_stats,
}
