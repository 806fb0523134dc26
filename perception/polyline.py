r"""Points against a polyline (the rope as the estimate's vertices draw it): where along it each
point's nearest point lies, and how far away.

The nearest point on edge :math:`k` from :math:`a_k` to :math:`b_k` is :math:`a_k + t\,(b_k - a_k)` with
:math:`t = \mathrm{clip}((p - a_k) \cdot (b_k - a_k) / |b_k - a_k|^2, 0, 1)`; a point belongs to the
edge whose nearest point is closest. The filter, the loss test and the length measure all use it.
"""

from __future__ import annotations

import numpy as np


def arc_positions(points: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length along the polyline ``x`` (k, 3) of each point's nearest point on it, and the distance.

    Args:
        points: (N, 3) [m].
        x: (k, 3) polyline, k >= 2 [m].

    Returns:
        ``(s, d)``: (N,) arc lengths from ``x[0]`` [m] and (N,) distances [m].
    """
    a, ab = x[:-1], np.diff(x, axis=0)
    length = np.linalg.norm(ab, axis=1)
    t = np.einsum("nkd,kd->nk", points[:, None] - a[None], ab) / np.maximum(length**2, 1e-12)
    t = np.clip(t, 0.0, 1.0)
    dist = np.linalg.norm(points[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1)  # (N, k-1)
    j = dist.argmin(1)
    start = np.concatenate([[0.0], np.cumsum(length)[:-1]])
    rows = np.arange(len(points))
    return start[j] + t[rows, j] * length[j], dist[rows, j]


def segment_distances(points: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the polyline through ``x`` (n, 3) [m]."""
    return arc_positions(points, x)[1]
