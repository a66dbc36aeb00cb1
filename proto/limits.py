"""What every part of the codec shares: the reasons a message is refused, the error that carries one,
and the limits that the field checks (:mod:`proto.codec`) and the cross-field checks
(:mod:`proto.validators`) both read."""
from __future__ import annotations

import re
from typing import Any, Final

MAX_STEPS: Final = 65536
"""Steps in one batch."""
MAX_LOCAL_EXAMPLES: Final = 64
"""Example transitions a LocalGraphReport may carry."""
REJECT_REASONS: Final = (
    "malformed", "unknown_type", "unexpected_type", "bad_version", "bad_field",
    "bad_array", "non_finite", "too_large", "inconsistent",
)
# Same alphabet as proto.topics, matched with fullmatch so a trailing newline is refused too.
KEY_SEGMENT: Final = re.compile(r"[A-Za-z0-9_.\-]+")


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


def require(ok: bool, reason: str, detail: str) -> None:
    if not ok:
        raise ProtocolError(reason, detail)


def short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
