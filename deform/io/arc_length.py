r"""A recording's markers as a model's vertices, and back, by arc length: for comparing a model
with recordings whose marker count differs (a calibrated model has the vertex count its user chose,
not the marker layout of a motion-capture set).

The gripped vertices (0, 1, n-2, n-1) are where the grippers hold the rope in both layouts and are
kept. The inner ones are placed along the free stretch between vertex 1 and vertex n-2, at the
arc-length fractions of the target's edges: with target edge lengths :math:`l_1 .. l_{n-3}` (its
free edges), vertex :math:`1 + k` sits at fraction :math:`\sum_{j \le k} l_j / \sum_j l_j` of the
source polyline's free arc, linearly interpolated between its points.

``curve="cubic"`` takes the fractions along a smooth curve through the source points instead: a
natural cubic spline :math:`p(c)` in their cumulative chord length :math:`c`, through all of them
(so the gripped end edges set its tangents at vertices 1 and n-2), its arc length measured on
:data:`FINE` samples per source edge. Why: a model's vertices and a recording's markers are samples
of one smooth rod. The polyline through either cuts each bend by its sagitta :math:`l^2 / 8R` (4 mm
for a 10 cm edge on a 30 cm radius), which, where the two layouts differ, reads as an error that
neither made; the spline's error falls as :math:`l^4`. A comparison of shapes uses it
(:mod:`deform.evaluate`); a tracker's start, needing only points near the rope, keeps the polyline.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

CURVES = ("linear", "cubic")
FINE = 16  # samples per source edge on which a cubic curve's arc length is measured


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


def resample_vertices(
    positions: np.ndarray, n: int, rest: np.ndarray | None = None, curve: str = "linear"
) -> np.ndarray:
    """``positions`` (..., m, 3) as ``n`` vertices along the same curve (see the module).

    Args:
        positions: vertices or markers, m >= 4, any leading axes (frames).
        n: vertices wanted.
        rest: (n-1,) edge lengths of the target layout (where its inner vertices sit), or None.
        curve: ``"linear"`` (the polyline through the points) or ``"cubic"`` (a spline through them).

    Returns:
        (..., n, 3); the gripped vertices are the source's.
    """
    if curve not in CURVES:
        raise ValueError(f"curve {curve!r}: one of {', '.join(CURVES)}")
    p = np.asarray(positions, dtype=np.float64)
    m = p.shape[-2]
    if m < 4:
        raise ValueError(f"{m} markers: at least 4 (two gripped at each end)")
    flat = p.reshape(-1, m, 3)
    target = free_fractions(rest, n)
    out = np.empty((len(flat), n, 3))
    out[:, [0, 1, -2, -1]] = flat[:, [0, 1, -2, -1]]
    for f in range(len(flat)):
        points = _free_curve(flat[f], curve)
        arc = np.concatenate([[0.0], np.cumsum(edge_lengths(points))])
        s = arc / arc[-1] if arc[-1] > 0 else np.linspace(0.0, 1.0, len(points))
        for d in range(3):
            out[f, 1 : n - 1, d] = np.interp(target, s, points[:, d])
    return out.reshape(*p.shape[:-2], n, 3)


def _free_curve(frame: np.ndarray, curve: str) -> np.ndarray:
    """Points along the free stretch (vertex 1 to m-2) of one frame (m, 3), in order: the frame's
    own for the polyline, :data:`FINE` per edge of the spline through all of them for ``cubic``
    (the polyline when two points coincide, where a chord parameter cannot grow)."""
    m = len(frame)
    free = frame[1 : m - 1]
    if curve == "linear":
        return free
    chord = np.concatenate([[0.0], np.cumsum(edge_lengths(frame))])
    if np.any(np.diff(chord) <= 1e-12):
        return free
    spline = CubicSpline(chord, frame, axis=0, bc_type="natural")
    return spline(np.linspace(chord[1], chord[m - 2], FINE * (m - 3) + 1))


def edge_lengths(frame: np.ndarray) -> np.ndarray:
    """(m-1,) edge lengths of one frame's polyline (m, 3): a recording's own marker layout."""
    return np.linalg.norm(np.diff(np.asarray(frame, dtype=np.float64), axis=0), axis=-1)
