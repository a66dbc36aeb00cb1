"""Zenoh key expressions: the only place topic names are spelled out.

``<run>`` is the run id. Who publishes and who subscribes is in the README's data-flow table.
"""
from __future__ import annotations

import re

ROOT = "causeway"
_SEGMENT = re.compile(r"^[A-Za-z0-9_.\-]+$")


def _check(*segments: str) -> None:
    for s in segments:
        if s != "*" and s != "**" and not _SEGMENT.fullmatch(s):
            raise ValueError(f"invalid key segment {s!r}: use letters, digits, '_', '.', '-'")


def env_spec(run: str) -> str:
    _check(run)
    return f"{ROOT}/{run}/env/spec"


def transitions(run: str, worker: str = "*") -> str:
    _check(run, worker)
    return f"{ROOT}/{run}/transitions/{worker}"


def frames(run: str, worker: str = "*") -> str:
    """Frames of env-worker ``worker`` (FrameBatch), for the factor-extractor."""
    _check(run, worker)
    return f"{ROOT}/{run}/frames/{worker}"


def frames_spec(run: str) -> str:
    """The EnvSpec of env-workers that publish frames (queryable); ``env/spec`` is then the
    factor-extractor's spec of the slot factors it publishes as transitions."""
    _check(run)
    return f"{ROOT}/{run}/env/frames"


def scored(run: str, worker: str = "*") -> str:
    _check(run, worker)
    return f"{ROOT}/{run}/scored/{worker}"


def skills(run: str, worker: str = "*") -> str:
    """SkiLD's skill-labelled transitions of env-worker ``worker`` (SkillBatch)."""
    _check(run, worker)
    return f"{ROOT}/{run}/skills/{worker}"


def induced(run: str, kind: str = "*", worker: str = "*") -> str:
    """Local graphs method ``kind``'s estimator induced for worker ``worker``'s batches (InducedGraphs)."""
    _check(run, kind, worker)
    return f"{ROOT}/{run}/induced/{kind}/{worker}"


def latent_actions(run: str, worker: str = "*") -> str:
    """FLAM's per-slot latent actions of env-worker ``worker``'s steps (LatentActions), from the factor-extractor."""
    _check(run, worker)
    return f"{ROOT}/{run}/latent/{worker}"


def weights(run: str, model: str = "*") -> str:
    _check(run, model)
    return f"{ROOT}/{run}/weights/{model}"


def graph(run: str, kind: str = "*") -> str:
    _check(run, kind)
    return f"{ROOT}/{run}/graph/{kind}"


def local(run: str, kind: str = "*") -> str:
    """Local-graph reports of method ``kind`` (LocalGraphReport)."""
    _check(run, kind)
    return f"{ROOT}/{run}/local/{kind}"


def control(run: str, service: str = "*") -> str:
    _check(run, service)
    return f"{ROOT}/{run}/control/{service}"


def stats(run: str, service: str = "*", instance: str = "*") -> str:
    _check(run, service, instance)
    return f"{ROOT}/{run}/stats/{service}/{instance}"


def alive(run: str, service: str = "*", instance: str = "*") -> str:
    _check(run, service, instance)
    return f"{ROOT}/{run}/alive/{service}/{instance}"


def parse_alive(key: str) -> tuple[str, str, str]:
    """``causeway/<run>/alive/<service>/<id>`` -> (run, service, id)."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != ROOT or parts[2] != "alive":
        raise ValueError(f"not a liveliness key: {key!r}")
    return parts[1], parts[3], parts[4]


def last_segment(key: str) -> str:
    return key.rsplit("/", 1)[-1]
