"""Raw parameters kept positive by softplus: the inverse map that starts them at a wanted value."""

from __future__ import annotations

import math


def inv_softplus(y: float) -> float:
    """``x`` with ``softplus(x) = y``: the raw value of a parameter kept positive by softplus.

    Args:
        y: the positive value wanted.

    Returns:
        The raw parameter value.
    """
    y = max(y, 1e-9)  # softplus never reaches 0: a massless marker is the smallest representable one
    return y + math.log(-math.expm1(-y))
