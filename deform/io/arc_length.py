r"""A recording's markers as a model's vertices, and back, by arc length: for comparing a model
with recordings whose marker count differs (a calibrated model has the vertex count its user chose,
not the marker layout of a motion-capture set).

The gripped vertices (0, 1, n-2, n-1) are where the grippers hold the rope in both layouts and are
kept. The inner ones are placed along the free stretch between vertex 1 and vertex n-2, at the
arc-length fractions of the target's edges: with target edge lengths :math:`l_1 .. l_{n-3}` (its
free edges), vertex :math:`1 + k` sits at fraction :math:`\sum_{j \le k} l_j / \sum_j l_j` of the
source polyline's free arc, linearly interpolated between its points.
"""

from __future__ import annotations

import numpy as np


def free_fractions(rest: np.ndarray | None, n: int) -> np.ndarray:
    """(n-2,) arc-length fractions (0..1) of vertices 1..n-2 along the free stretch.

    Args:
        rest: (n-1,) edge lengths of the target layout, or None for evenly spaced inner vertices.
        n: the target's vertex count (at least 4).

    Returns:
        Increasing fractions from 0 (vertex 1) to 1 (vertex n-2).

    Raises:
        ValueError: fewer than 4 vertices, or ``rest`` of the wrong length or not positive.
    """
    if n < 4:
        raise ValueError(f"{n} vertices: at least 4 (two gripped at each end)")
    if rest is None:
        return np.linspace(0.0, 1.0, n - 2)
    rest = np.asarray(rest, dtype=np.float64)
    if rest.shape != (n - 1,) or not np.all(rest[1:-1] > 0):
        raise ValueError(f"rest lengths of shape {rest.shape} for {n} vertices (need {n - 1} positive)")
    s = np.concatenate([[0.0], np.cumsum(rest[1:-1])])
    return s / s[-1]


def resample_vertices(positions: np.ndarray, n: int, rest: np.ndarray | None = None) -> np.ndarray:
    """``positions`` (..., m, 3) as ``n`` vertices along the same polyline (see the module).

    Args:
        positions: vertices or markers, m >= 4, any leading axes (frames).
        n: vertices wanted.
        rest: (n-1,) edge lengths of the target layout (where its inner vertices sit), or None.

    Returns:
        (..., n, 3); the gripped vertices are the source's.
    """
    p = np.asarray(positions, dtype=np.float64)
    m = p.shape[-2]
    if m < 4:
        raise ValueError(f"{m} markers: at least 4 (two gripped at each end)")
    flat = p.reshape(-1, m, 3)
    target = free_fractions(rest, n)
    out = np.empty((len(flat), n, 3))
    out[:, [0, 1, -2, -1]] = flat[:, [0, 1, -2, -1]]
    free = flat[:, 1 : m - 1]
    arc = np.concatenate(
        [np.zeros((len(flat), 1)), np.cumsum(np.linalg.norm(np.diff(free, axis=1), axis=-1), axis=1)], 1
    )
    for f in range(len(flat)):
        s = arc[f] / arc[f, -1] if arc[f, -1] > 0 else np.linspace(0.0, 1.0, m - 2)
        for d in range(3):
            out[f, 1 : n - 1, d] = np.interp(target, s, free[f, :, d])
    return out.reshape(*p.shape[:-2], n, 3)


def edge_lengths(frame: np.ndarray) -> np.ndarray:
    """(m-1,) edge lengths of one frame's polyline (m, 3): a recording's own marker layout."""
    return np.linalg.norm(np.diff(np.asarray(frame, dtype=np.float64), axis=0), axis=-1)
