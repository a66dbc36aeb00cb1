"""Codec contract: every off-contract payload is rejected with its own reason."""
from __future__ import annotations

import ast
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from proto import REJECT_REASONS, SCHEMA_VERSION, Control, EnvSpec, GraphReport, LocalGraphReport, ProtocolError
from proto import ScoredBatch, ServiceStats, TransitionBatch, Weights, codec, encode

from tests.proto.samples import (
    Mutation, SAMPLES, control, env_spec, graph_report, local_report,
    raw_of, reason_of, transitions, wire,
)


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
LOCAL = local_report()
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
        ("next version", Control, put("schema_version", SCHEMA_VERSION + 1)),
        ("previous version", Control, put("schema_version", SCHEMA_VERSION - 1)),
        ("no version", Control, drop("schema_version")),
        ("version bool", Control, put("schema_version", True)),
        ("version float", Control, put("schema_version", 1.0)),
        ("nested version", ScoredBatch, put("transitions.schema_version", 0)),
        ("report before standard errors (v4)", GraphReport,
         lambda raw: [raw.pop(k) for k in ("cmi_stderr", "undecided", "edge_rule", "fdr", "min_cmi")]
         + [raw.update(schema_version=4)]),
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
        ("report without edge rule", GraphReport, drop("edge_rule")),
        ("unknown edge rule", GraphReport, put("edge_rule", "oracle")),
        ("fdr of 1", GraphReport, put("fdr", 1.0)),
        ("negative min_cmi", GraphReport, put("min_cmi", -1e-3)),
    ],
    "non_finite": [
        ("NaN state", TransitionBatch, put("state", nan_at(T.state))),
        ("inf reward", TransitionBatch, put("reward", nan_at(T.reward, np.inf))),
        ("NaN intrinsic", ScoredBatch, put("intrinsic_reward", nan_at(F32_4))),
        ("NaN tensor", Weights, put("tensors.b", nan_at(np.zeros(2)))),
        ("inf cmi", GraphReport, put("cmi", nan_at(REPORT.cmi, -np.inf))),
        ("NaN reward score", GraphReport, put("reward_scores", nan_at(REPORT.reward_scores))),
        ("NaN threshold", GraphReport, put("threshold", float("nan"))),
        ("NaN standard error", GraphReport, put("cmi_stderr", nan_at(REPORT.cmi_stderr))),
        ("inf metric", GraphReport, put("metrics.f1", float("inf"))),
        ("NaN local score", LocalGraphReport, put("scores", nan_at(LOCAL.scores))),
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
        ("option below -1", TransitionBatch, put("option", wire(T.option - 2))),
        ("option int64", TransitionBatch, put("option", wire(T.option.astype(np.int64)))),
        ("adjacency 2", GraphReport, put("adjacency", wire(2 * REPORT.adjacency))),
        ("true graph 2", GraphReport, put("true_graph", wire(2 * REPORT.adjacency))),
        ("reward parents 2", GraphReport, put("reward_parents", wire(2 * REPORT.reward_parents))),
        ("reward parents 2-D", GraphReport, put("reward_parents", wire(REPORT.reward_parents[None]))),
        ("spec reward parents 2", EnvSpec, put("reward_parents", wire(2 * SPEC.reward_parents))),
        ("negative standard error", GraphReport, put("cmi_stderr", wire(-REPORT.cmi_stderr))),
        ("undecided 2", GraphReport, put("undecided", wire(2 * REPORT.undecided))),
    ],
    "too_large": [
        ("declared shape oversize", TransitionBatch, put("state.shape", [2**25, 1])),
        ("tensor oversize", Weights, put("tensors.u8.shape", [2**24 + 1])),
        ("string > 1 MiB", Control, put("argument", "x" * (2**20 + 1))),
        ("too many local examples", LocalGraphReport,
         lambda raw: (put("scores", wire(np.zeros((65, 3, 4), np.float32)))(raw),
                      put("truth", wire(np.zeros((65, 3, 4), np.uint8)))(raw))),
    ],
    "inconsistent": [
        ("local scores shape", LocalGraphReport, put("scores", wire(LOCAL.scores[:, :2]))),
        ("local truth count", LocalGraphReport, put("truth", wire(LOCAL.truth[:1]))),
        ("next_state shape", TransitionBatch, put("next_state", wire(T.state[:, :2]))),
        ("action rows", TransitionBatch, put("action", wire(T.action[:3]))),
        ("reward length", TransitionBatch, put("reward", wire(T.reward[:3]))),
        ("episode_id length", TransitionBatch, put("episode_id", wire(I64_5))),
        ("local graph square", TransitionBatch, put("local_graph", wire(T.local_graph[..., :2]))),
        ("local graph rows", TransitionBatch, put("local_graph", wire(T.local_graph[:3]))),
        ("option length", TransitionBatch, put("option", wire(T.option[:3]))),
        ("intrinsic length", ScoredBatch, put("intrinsic_reward", wire(F32_5))),
        ("sizes short", EnvSpec, put("factor_sizes", [2, 2])),
        ("scales long", EnvSpec, put("factor_scales", [1.0] * 4)),
        ("global graph square", EnvSpec, put("global_graph", wire(np.eye(3, dtype="u1")))),
        ("cmi shape", GraphReport, put("cmi", wire(np.zeros((3, 3), np.float32)))),
        ("adjacency shape", GraphReport, put("adjacency", wire(np.zeros((4, 5), "u1")))),
        ("true graph shape", GraphReport, put("true_graph", wire(np.zeros((2, 3), "u1")))),
        ("classes overlap", GraphReport, put("action_relevant", [0, 1])),
        ("class duplicates", GraphReport, put("controllable", [0, 0])),
        ("reward parents without scores", GraphReport, put("reward_scores", None)),
        ("reward scores without parents", GraphReport, put("reward_parents", None)),
        ("reward scores length", GraphReport, put("reward_scores", wire(F32_5))),
        ("reward parents length", GraphReport, put("reward_parents", wire(np.zeros(3, "u1")))),
        ("true reward parents length", GraphReport, put("true_reward_parents", wire(np.zeros(5, "u1")))),
        ("spec reward parents length", EnvSpec, put("reward_parents", wire(np.zeros(3, "u1")))),
        ("standard error shape", GraphReport, put("cmi_stderr", wire(np.zeros((3, 3), np.float32)))),
        ("undecided shape", GraphReport, put("undecided", wire(np.zeros((3, 3), "u1")))),
        ("standard errors without undecided", GraphReport, put("undecided", None)),
        ("fdr rule without standard errors", GraphReport,
         lambda raw: (put("cmi_stderr", None)(raw), put("undecided", None)(raw))),
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


def test_a_payload_of_nested_empty_containers_is_refused_while_unpacking() -> None:
    import tracemalloc

    # {"type": [[{}, {}, ...], ...]}: 16 MiB of empty maps, within the size cap
    lists = (b"\xdc\xff\xff" + b"\x80" * 0xFFFF) * 256
    bomb = b"\x81\xa4type" + b"\xdc\x01\x00" + lists
    tracemalloc.start()
    try:
        assert reason_of(bomb) == "too_large"
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20, f"{peak / 2**20:.0f} MiB to refuse it"
    assert reason_of(msgpack.packb([1, 2, 3])) == "malformed"  # not a map: refused before parsing


def test_an_empty_array_with_an_impossible_dimension_is_a_protocol_error() -> None:
    raw = raw_of(env_spec())
    raw["global_graph"] = {"dtype": "uint8", "shape": [0, 2**63 - 1], "data": b""}
    assert reason_of(msgpack.packb(raw)) == "too_large"
