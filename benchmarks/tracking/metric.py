"""The tracking error of the field (TrackDLO's protocol): the mean two-way distance between the tracked
nodes and the true rope, so that trackers with different node counts compare.

``error = 0.5 * (mean over tracked nodes of the distance to the true polyline
               + mean over the true polyline, sampled densely, of the distance to the tracked polyline)``

Two truths: the marker polyline (the motion-capture markers joined by straight edges) and the rope
as rendered (:func:`rope_error`: the curve the clouds were drawn from). Against the markers a model
whose vertices sit at the markers scores 0 for a perfect shape while any other node layout cannot
(the camera shows a curve 1-3 mm off the chords of a bent rope): that measures the node layout, not
the tracking. The rendered rope is the same truth for every method.
"""

from __future__ import annotations

import numpy as np

SAMPLES_PER_EDGE = 10


def densify(polyline: np.ndarray, per_edge: int = SAMPLES_PER_EDGE) -> np.ndarray:
    """Points along a polyline, ``per_edge`` per edge (both ends included).

    Args:
        polyline: (n, 3) vertices.
        per_edge: samples per edge.

    Returns:
        ((n - 1) per_edge + 1, 3).
    """
    p = np.asarray(polyline, dtype=np.float64)
    s = np.arange(per_edge) / per_edge
    inner = p[:-1, None] + s[None, :, None] * (p[1:] - p[:-1])[:, None]
    return np.concatenate([inner.reshape(-1, 3), p[-1:]])


def point_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """(m,) distance of each point to the nearest point of a polyline's edges.

    Args:
        points: (m, 3).
        polyline: (n, 3), n >= 1.

    Returns:
        (m,) distances [same unit].
    """
    q = np.asarray(points, dtype=np.float64)
    p = np.asarray(polyline, dtype=np.float64)
    if len(p) == 1:
        return np.linalg.norm(q - p[0], axis=1)
    a, e = p[:-1], p[1:] - p[:-1]  # (k, 3)
    ee = np.maximum((e * e).sum(1), 1e-18)
    t = np.clip(((q[:, None] - a[None]) * e[None]).sum(-1) / ee[None], 0.0, 1.0)  # (m, k)
    nearest = a[None] + t[..., None] * e[None]
    return np.linalg.norm(q[:, None] - nearest, axis=-1).min(1)


def two_way_error(tracked: np.ndarray, truth: np.ndarray, per_edge: int = SAMPLES_PER_EDGE) -> float:
    """The mean two-way distance between tracked nodes and the true rope [same unit as the inputs].

    Args:
        tracked: (k, 3) tracked nodes, in order along the rope.
        truth: (n, 3) true vertices (k and n may differ).
        per_edge: samples per true edge for the second half.

    Returns:
        0.5 (mean tracked-to-true-polyline + mean dense-true-to-tracked-polyline).
    """
    a = point_to_polyline(tracked, truth).mean()
    b = point_to_polyline(densify(truth, per_edge), tracked).mean()
    return float(0.5 * (a + b))


def rope_error(tracked: np.ndarray, markers: np.ndarray, per_segment: int = 8) -> float:
    """The two-way distance between tracked nodes and the rope the clouds show: the renderer's
    centreline through the markers (``perception.rope_centreline``), ``per_segment`` points per
    marker interval.

    Args:
        tracked: (k, 3) tracked nodes, in order along the rope.
        markers: (n, 3) the true markers the rope was rendered through.
        per_segment: curve points per marker interval.

    Returns:
        The error [same unit as the inputs].
    """
    from perception import rope_centreline

    return two_way_error(tracked, rope_centreline(np.asarray(markers, dtype=np.float64), per_segment), 1)


def recovery_time(times: np.ndarray, errors: np.ndarray, start: float, end: float, factor: float = 2.0):
    """Seconds after the rope is visible again (``end``) until the error is back within ``factor`` x
    the mean error of the second before the blackout (``start - 1`` to ``start``).

    Args:
        times: (F,) camera frame times [s].
        errors: (F,) errors.
        start: when the blackout began [s].
        end: when the rope was visible again [s].
        factor: the tolerance on the error before.

    Returns:
        ``(recovery_s, reference)``: recovery_s None when the error never came back; reference the
        mean error of the second before.
    """
    times, errors = np.asarray(times, dtype=np.float64), np.asarray(errors, dtype=np.float64)
    before = (times >= start - 1.0) & (times < start)
    if not before.any():
        return None, None
    ref = float(errors[before].mean())
    after = np.flatnonzero((times >= end - 1e-9) & (errors <= factor * ref))
    if len(after) == 0:
        return None, ref
    return float(times[after[0]] - end), ref
