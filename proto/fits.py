"""Whether a transition batch fits the run's environment: its layout (the EnvSpec's widths and local
graphs) and its values (category indices, the env's declared observation space). Decoding checks a
message on its own; every consumer of transitions checks this before storing anything, so data the
env cannot produce (a forged or corrupted batch of 3e38 positions) never reaches a model or a
checkpoint (issue 20)."""
from __future__ import annotations

import numpy as np

from proto.codec import ProtocolError
from proto.messages import EnvSpec, TransitionBatch


def check_fits(spec: EnvSpec, batch: TransitionBatch) -> None:
    """Raise ProtocolError('inconsistent') unless ``batch`` has the layout ``spec`` announces.

    Decoding checks a message on its own; this checks it against the run's EnvSpec, which every
    consumer of transitions does before storing anything.
    """
    if batch.state.shape[1] != spec.state_dim or batch.action.shape[1] != spec.action_dim:
        raise ProtocolError("inconsistent", f"TransitionBatch from {batch.worker_id}: state/action widths "
                            f"{batch.state.shape[1]}/{batch.action.shape[1]}, EnvSpec says {spec.state_dim}/{spec.action_dim}")
    graphs = batch.local_graph
    if graphs is not None and graphs.shape[1:] != (spec.num_factors, spec.num_factors + 1):
        raise ProtocolError("inconsistent", f"TransitionBatch from {batch.worker_id}: local graphs {graphs.shape[1:]}")
    for name in ("state", "next_state"):
        _check_in_space(spec, getattr(batch, name), f"TransitionBatch from {batch.worker_id}: {name}")
    if spec.action_kind == "categorical":
        _check_categories(batch.action[:, 0], spec.action_size, f"TransitionBatch from {batch.worker_id}: action")


def _check_in_space(spec: EnvSpec, states: np.ndarray, what: str) -> None:
    """ProtocolError('inconsistent') for factor values the env cannot produce: a categorical factor's
    slot must hold a category index, every slot must lie within the declared bounds (where given)."""
    column = 0
    for kind, size in zip(spec.factor_kinds, spec.factor_sizes):
        if kind == "categorical":
            _check_categories(states[:, column], size, f"{what} column {column}")
        column += 1 if kind == "categorical" else size
    if spec.state_low is not None:
        outside = (states < spec.state_low) | (states > spec.state_high)
        if outside.any():
            row, col = (int(i[0]) for i in np.nonzero(outside))
            raise ProtocolError("inconsistent", f"{what}: {int(outside.sum())} values outside the env's observation "
                                f"space (column {col}: {states[row, col]:.6g} not in "
                                f"[{spec.state_low[col]:.6g}, {spec.state_high[col]:.6g}])")


def _check_categories(values: np.ndarray, size: int, what: str) -> None:
    bad = (values < 0) | (values >= size) | (values != np.floor(values))
    if bad.any():
        raise ProtocolError("inconsistent", f"{what}: {repr(float(values[bad][0]))} is no category index of {size}")
