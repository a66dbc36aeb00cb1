"""How the summary writes floats it keeps for people and scripts: to significant digits, not decimals.

Decimals lose the small entries: a CMI of 3e-6 nats rounded to 5 decimals is 0, and the fdr rule's
level and the ``mirror`` bias are read from entries that small (issue 22)."""
from __future__ import annotations

import numpy as np


def significant(values: np.ndarray, digits: int) -> list:
    """``values`` as nested lists of floats rounded to ``digits`` significant digits."""
    return [float(f"{v:.{digits}g}") for v in np.asarray(values, dtype=float).ravel()] if np.ndim(values) == 1 \
        else [significant(row, digits) for row in np.asarray(values, dtype=float)]
