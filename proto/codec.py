"""msgpack codec for ``proto.messages``, with validation of everything that comes off the wire.

Wire format: one msgpack map ``{"type", "schema_version", <every dataclass field>}``. A numpy array
travels as ``{"dtype": name, "shape": [ints], "data": C-order little-endian bytes}``, a tuple as a
list, ``Weights.tensors`` as a map of array maps, and ``ScoredBatch.transitions`` as a full nested
``TransitionBatch`` map (its own type and version are checked). No pickle anywhere.

``decode`` checks, in order: payload size, msgpack framing, ``type``, ``expected``,
``schema_version``, the field set, each field's Python type (arrays: dtype, ndim, size, bytes,
finiteness), then the message's cross-field rules (:mod:`proto.validators`). Any failure raises
``ProtocolError`` whose ``reason`` is one of ``REJECT_REASONS``, a bounded set used as the ``reason`` label of
``causeway_messages_rejected_total``. Decoded arrays are fresh, writeable, native-order copies.
``encode`` trusts its input (the receiver validates) but refuses dtypes that cannot travel.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import fields
from typing import Any, Final, TypeVar, overload

import msgpack
import numpy as np

from proto.limits import MAX_STEPS, REJECT_REASONS, ProtocolError
from proto.limits import require as _require
from proto.limits import short as _short
from proto.messages import MESSAGE_TYPES, SCHEMA_VERSION
from proto.messages import (Control, EnvSpec, FrameBatch, GraphReport, InducedGraphs, LatentActions, LocalGraphReport,
                            ScoredBatch, ServiceStats, SkillBatch, TransitionBatch, Weights)
from proto.validators import VALIDATORS as _VALIDATORS

__all__ = ["ARRAY_DTYPES", "MAX_ARRAY_ELEMENTS", "MAX_CONTAINERS", "MAX_CONTAINER_LEN", "MAX_MESSAGE_BYTES", "MAX_NDIM",
           "MAX_STEPS", "MAX_STR_BYTES", "REJECT_REASONS", "Message", "ProtocolError", "decode", "encode"]

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
MAX_NDIM: Final = 8
ARRAY_DTYPES: Final = ("float32", "float64", "int32", "int64", "uint8", "bool")

_HEADER_KEYS: Final = frozenset({"type", "schema_version"})
_ARRAY_KEYS: Final = frozenset({"dtype", "shape", "data"})


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
        "reward_undecided": _optional(_PARENTS), "reward_min_cmi": _float,
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
    LatentActions: {
        "kind": _str, "worker_id": _str, "seq": _int, "weights_version": _int,
        "episode_id": _array("int64", ndim=1), "step": _array("int32", ndim=1),
        "mean": _array("float32", ndim=3), "log_sigma": _array("float32", ndim=3),
    },
    Control: {"command": _str, "argument": _str, "issued_at": _float},
    ServiceStats: {
        "service": _str, "instance": _str, "values": _str_map(_float), "timestamp": _float,
    },
}
