"""What a consumer accepts from the bus beyond a message's own validity (issue 20): versions that
move forward by bounded steps from the last accepted one of the same publisher, and weights whose
model configuration is the run's and describes exactly the tensors the message carries, checked
before any model is built. Pure: no bus, no metrics (the shells count the refusals).

Roles on the bus stop strangers and wrong roles; these checks stop a message of the right role that
a faulty or compromised publisher got wrong: a forged version 2**62 would otherwise make every later
(real) version look stale forever, and a 1.3 KB message whose configuration names large widths would
allocate gigabytes before its tensors were found not to fit.
"""
from __future__ import annotations

import json
from dataclasses import asdict
from typing import TYPE_CHECKING, Any, Callable, Final, Mapping

import numpy as np

from proto.codec import ProtocolError

if TYPE_CHECKING:  # torch is imported where a model is checked: an env-worker without a policy never loads it
    from torch import nn

    from causal.factored import FactorLayout

MAX_VERSION_STEP: Final = 10_000
"""Largest step a publisher's version may take from its last accepted one. Versions move by one per
publication (a restarted learner continues above its high-water mark), so a consumer would have to
miss this many publications in a row (hours at a publication per second) to refuse a real one."""


UNKNOWN: Final = -1
"""``known`` of a :class:`VersionGate` (and ``known_version`` of a service) when no version is known
published: the first version of each publisher is taken as it comes."""


class VersionGate:
    """The last accepted version of each publisher; a new version must be newer, by at most ``max_step``.

    A publisher's *first* version is bounded too: at most ``max_step`` above ``known``, a version this
    consumer knows was published without taking the publisher's word for it: its own checkpoint's last
    accepted version (:meth:`know`), or the one the supervisor read for it when it started it
    (``known_version`` of its configuration: the dynamics-learner's record of its published versions,
    which it writes before it publishes, or the policy-learner's last beat). Versions only grow (a
    restarted learner continues above any it published), so a real first version is never below
    ``known``, and a consumer that joins a run within ``max_step`` publications of that is not refused;
    a forged 2**62 is. A refused version is ``ProtocolError('inconsistent')``; the last accepted version
    stays, so the real publisher's next versions are still taken.

    ``known`` :data:`UNKNOWN` (-1): nothing is known (a compose or Kubernetes service with no checkpoint
    yet, where no supervisor reads the learner's record): a publisher's first version is taken as it
    comes and only the steps after it are bounded. Refusing instead would lock out, for good, a
    consumer that restarts without a checkpoint once the run is past ``max_step`` publications; the
    bus roles are what keeps a stranger from publishing weights there (docs/bus-roles.md)."""

    def __init__(self, max_step: int = MAX_VERSION_STEP, known: int = 0) -> None:
        if max_step < 1:
            raise ValueError(f"max_step must be >= 1, got {max_step}")
        if known < UNKNOWN:
            raise ValueError(f"known must be >= 0, or {UNKNOWN} for not known, got {known}")
        self.max_step = max_step
        self.known = known
        self.last: dict[str, int] = {}

    def know(self, version: int) -> None:
        """Record ``version`` as known published (a checkpoint's), raising the bound on first versions."""
        self.known = max(self.known, int(version))

    def newer(self, publisher: str, version: int, ceiling: int | None = None) -> bool:
        """True for a version above the last accepted one (within the bound; not yet accepted: call
        :meth:`accept` once the message is used), False for a repeat or an older one (ignore it).
        ``ProtocolError`` for a jump beyond the bound, from the last accepted version or, for the
        publisher's first, from ``known``, and for a version above ``ceiling``, where the consumer knows
        the highest one published (the learner its own, the supervisor the learner's record)."""
        if ceiling is not None and version > ceiling:
            raise ProtocolError("inconsistent", f"{publisher} version {version} was never published (the highest "
                                                f"published is {ceiling})")
        last = self.last.get(publisher)
        base = self.known if last is None else last
        if base != UNKNOWN and version > base + self.max_step:
            since = f"the last accepted {last}" if last is not None else f"the {base} known published (first version)"
            raise ProtocolError("inconsistent", f"{publisher} version {version} jumps more than {self.max_step} "
                                                f"past {since}")
        return last is None or version > last

    def accept(self, publisher: str, version: int) -> None:
        """Record ``version`` as the publisher's last accepted one."""
        self.last[publisher] = version

    def take(self, publisher: str, version: int, ceiling: int | None = None) -> bool:
        """:meth:`newer`, and :meth:`accept` when it is: for a message used as soon as it is checked."""
        if not self.newer(publisher, version, ceiling):
            return False
        self.accept(publisher, version)
        return True


def check_weights_config(config_json: str, tensors: Mapping[str, np.ndarray], method: str, layout: "FactorLayout",
                         build: "Callable[[str], nn.Module]") -> None:
    """``ValueError`` unless ``config_json`` is a model of the run's ``method`` for the run's factor
    ``layout`` whose parameters are exactly ``tensors`` (names and shapes). The model is built on
    torch's meta device, which allocates no memory, so a configuration that names large widths is
    refused for the few bytes its message carries, never allocated. ``build``: the config JSON -> a model
    (``causal.methods.model_from_config_json``)."""
    config = _parse(config_json)
    if config.get("model") != method:
        raise ValueError(f"weights of method {config.get('model')!r}, this run's is {method!r}")
    if config.get("layout") != json.loads(json.dumps(asdict(layout))):
        raise ValueError(f"weights for another factor layout than this run's ({_short(config.get('layout'))})")
    check_tensor_shapes(lambda: {name: tuple(p.shape) for name, p in build(config_json).named_parameters()}, tensors,
                        "the model configuration")


def check_tensor_shapes(describe: "Callable[[], Mapping[str, tuple[int, ...]]]", tensors: Mapping[str, np.ndarray],
                        what: str) -> None:
    """``ValueError`` unless the names and shapes ``describe()`` gives, run on torch's meta device (it
    builds a model that allocates nothing), are exactly those of ``tensors``."""
    import torch

    with torch.device("meta"):
        shapes = dict(describe())
    carried = {name: tuple(array.shape) for name, array in tensors.items()}
    if shapes != carried:
        differ = sorted(n for n in set(shapes) | set(carried) if shapes.get(n) != carried.get(n))
        raise ValueError(f"{what} describes {sum(int(np.prod(s)) for s in shapes.values()):,} parameters, the "
                         f"message carries {sum(a.size for a in tensors.values()):,}; they differ at {', '.join(differ[:3])}")


def _parse(config_json: str) -> dict[str, Any]:
    try:
        config = json.loads(config_json)
    except ValueError as exc:
        raise ValueError(f"model configuration is not JSON: {exc}") from None
    if not isinstance(config, dict):
        raise ValueError("model configuration is not a JSON object")
    return config


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 80 else text[:77] + "..."
