"""A first guess of the rod from the gripper poses and the visible rope points.

The free part hangs as a parabola of the right arc length below the chord between the inner gripped
vertices; the plane of that parabola is turned about the chord to the angle that best explains the
visible points. The tracker then lets the model settle from this guess (grippers fixed), which fills
in the occluded vertices with a physically plausible shape.
"""

from __future__ import annotations

import numpy as np

from deform import gripped_indices


def _parabola_length(chord: float, sag: float, samples: int = 64) -> float:
    s = np.linspace(0, 1, samples)
    y = 4 * sag * s * (1 - s)
    return float(np.hypot(np.diff(s * chord), np.diff(y)).sum())


def hanging_curve(a: np.ndarray, b: np.ndarray, length: float, angle: float, samples: int = 64) -> np.ndarray:
    """(samples, 3) a parabola from ``a`` to ``b`` of arc length ``length``, sagging below the chord,
    its plane turned by ``angle`` about the chord from the vertical.

    Args:
        a: (3,) one end [m].
        b: (3,) the other end [m].
        length: arc length of the curve [m].
        angle: turn of the curve's plane about the chord [rad].
        samples: points on the curve.

    Returns:
        (samples, 3).
    """
    c = b - a
    chord = float(np.linalg.norm(c))
    axis = c / max(chord, 1e-9)
    down = np.array([0.0, 0.0, -1.0]) - axis * (-axis[2])
    if np.linalg.norm(down) < 1e-6:
        down = np.cross(axis, [1.0, 0.0, 0.0])
    down /= np.linalg.norm(down)
    side = np.cross(axis, down)
    direction = np.cos(angle) * down + np.sin(angle) * side
    lo, hi = 0.0, max(length, 1e-3)
    if length > chord:
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if _parabola_length(chord, mid) < length else (lo, mid)
    s = np.linspace(0, 1, samples)
    return a + s[:, None] * c + (4 * lo * s * (1 - s))[:, None] * direction


def place_by_arclength(curve: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Points along ``curve`` at cumulative distances ``spacing`` (scaled to fit the curve).

    Args:
        curve: (M, 3) a polyline [m].
        spacing: (k,) distances between consecutive points [m].

    Returns:
        (k + 1, 3) points along the curve.
    """
    seg = np.linalg.norm(np.diff(curve, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    target = np.concatenate([[0.0], np.cumsum(spacing)])
    target *= s[-1] / max(target[-1], 1e-12)
    return np.stack([np.interp(target, s, curve[:, k]) for k in range(3)], axis=1)


def initial_guess(
    grip: np.ndarray, rest: np.ndarray, points: np.ndarray | None = None, n_angles: int = 19
) -> np.ndarray:
    """(n, 3) guess: gripped vertices from ``grip`` (4, 3), the free part hanging, turned towards ``points``.

    Args:
        grip: (4, 3) vertices 0, 1, n-2, n-1 [m].
        rest: (n-1,) rest lengths [m].
        points: (N, 3) rope points to turn towards, world frame, or None.
        n_angles: turns of the hanging plane tried when there are points.

    Returns:
        (n, 3) vertices [m].
    """
    n = len(rest) + 1
    inner = rest[1 : n - 2]
    best, best_cost = None, np.inf
    angles = (
        np.linspace(-np.pi * 0.45, np.pi * 0.45, n_angles) if points is not None and len(points) else [0.0]
    )
    for ang in angles:
        curve = hanging_curve(grip[1], grip[2], float(inner.sum()), float(ang))
        if points is None or len(points) == 0:
            best = curve
            break
        d = np.linalg.norm(points[:, None] - curve[None], axis=-1).min(1)
        cost = np.minimum(d, 0.05).mean()
        if cost < best_cost:
            best, best_cost = curve, cost
    x = np.empty((n, 3))
    x[gripped_indices(n)] = grip
    x[1 : n - 1] = place_by_arclength(best, inner)
    x[1], x[n - 2] = grip[1], grip[2]
    return x
