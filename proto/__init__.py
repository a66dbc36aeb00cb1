"""The wire contract: message schemas (``messages``), topic names (``topics``), the ``codec``."""
from proto.codec import REJECT_REASONS, Message, ProtocolError, decode, encode
from proto.messages import (
    SCHEMA_VERSION,
    Control,
    EnvSpec,
    FrameBatch,
    GraphReport,
    LocalGraphReport,
    ScoredBatch,
    ServiceStats,
    TransitionBatch,
    Weights,
)

__all__ = [
    "REJECT_REASONS",
    "SCHEMA_VERSION",
    "Control",
    "EnvSpec",
    "FrameBatch",
    "GraphReport",
    "LocalGraphReport",
    "Message",
    "ProtocolError",
    "ScoredBatch",
    "ServiceStats",
    "TransitionBatch",
    "Weights",
    "decode",
    "encode",
]
