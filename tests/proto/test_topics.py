"""Topic names: the key each function builds, segment validation, and liveliness-key parsing."""
from __future__ import annotations

from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from proto import topics

segments = st.from_regex(r"[A-Za-z0-9_.\-]{1,16}", fullmatch=True)
BAD_SEGMENTS = ["", "a/b", "a b", "ünï", "a*", "x**", "$x", "a#b", "a?b", "/"]


@pytest.mark.parametrize(
    "key, expected",
    [
        (topics.env_spec("r1"), "causeway/r1/env/spec"),
        (topics.transitions("r1"), "causeway/r1/transitions/*"),
        (topics.transitions("r1", "w-0"), "causeway/r1/transitions/w-0"),
        (topics.scored("r1"), "causeway/r1/scored/*"),
        (topics.scored("r1", "w-0"), "causeway/r1/scored/w-0"),
        (topics.weights("r1"), "causeway/r1/weights/*"),
        (topics.weights("r1", "policy"), "causeway/r1/weights/policy"),
        (topics.graph("r1"), "causeway/r1/graph/*"),
        (topics.graph("r1", "cdl"), "causeway/r1/graph/cdl"),
        (topics.control("r1"), "causeway/r1/control/*"),
        (topics.control("r1", "env-worker"), "causeway/r1/control/env-worker"),
        (topics.stats("r1"), "causeway/r1/stats/*/*"),
        (topics.stats("r1", "env-worker", "3"), "causeway/r1/stats/env-worker/3"),
        (topics.alive("r1"), "causeway/r1/alive/*/*"),
        (topics.alive("r1", "env-worker", "3"), "causeway/r1/alive/env-worker/3"),
        (topics.alive("run_2024.01", "**"), "causeway/run_2024.01/alive/**/*"),
        (topics.env_spec("*"), "causeway/*/env/spec"),
    ],
)
def test_key(key: str, expected: str) -> None:
    assert key == expected


ONE_SEGMENT: list[Callable[[str], str]] = [
    topics.env_spec,
    lambda s: topics.transitions("r", s),
    lambda s: topics.scored("r", s),
    lambda s: topics.weights("r", s),
    lambda s: topics.graph("r", s),
    lambda s: topics.control("r", s),
    lambda s: topics.stats("r", s),
    lambda s: topics.stats("r", "svc", s),
    lambda s: topics.alive("r", s),
    lambda s: topics.alive("r", "svc", s),
    lambda s: topics.transitions(s),
]


@pytest.mark.parametrize("segment", BAD_SEGMENTS)
@pytest.mark.parametrize("make", ONE_SEGMENT)
def test_invalid_segment_raises(make: Callable[[str], str], segment: str) -> None:
    with pytest.raises(ValueError, match="invalid key segment"):
        make(segment)


def test_trailing_newline_is_an_invalid_segment() -> None:
    with pytest.raises(ValueError):
        topics.transitions("r", "w\n")


@settings(max_examples=50, deadline=None)
@given(run=segments, service=segments, instance=segments)
def test_parse_alive_inverts_alive(run: str, service: str, instance: str) -> None:
    key = topics.alive(run, service, instance)
    assert topics.parse_alive(key) == (run, service, instance)
    assert topics.last_segment(key) == instance


@pytest.mark.parametrize(
    "key",
    [
        "causeway/r/alive/svc",
        "causeway/r/alive/svc/0/extra",
        "other/r/alive/svc/0",
        "causeway/r/stats/svc/0",
        "",
    ],
)
def test_parse_alive_rejects_other_keys(key: str) -> None:
    with pytest.raises(ValueError, match="not a liveliness key"):
        topics.parse_alive(key)


def test_last_segment() -> None:
    assert topics.last_segment(topics.weights("r", "policy")) == "policy"
    assert topics.last_segment("single") == "single"
