"""The geometry the independent simulators (PyElastica: benchmarks/planted/elastica.py, MuJoCo:
benchmarks/planted/mujoco.py) share: where the markers sit on the rope, which nodes the grips hold,
the rope's starting curve through the first frame's markers, the grippers' smoothed trajectory with
its lead-in from rest, and parallel transport of a frame's normal."""

from __future__ import annotations

import math

import numpy as np

from deform.io.recordings import Recording

LEAD_FRAMES = 20  # grips ramp from rest to their first recorded velocity over this lead-in


def marker_layout(sources: list[Recording], length_m: float) -> tuple[np.ndarray, float]:
    """Material arc length [m] of each marker on the rod, and the tail beyond each outer marker.

    Marker spacings are the median edge lengths over the sources; the rope's length beyond the
    marker span is split evenly into two free tails (the grippers hold the rope between its two end
    markers; what runs past the outer marker hangs free)."""
    edges = np.concatenate([np.linalg.norm(np.diff(r.positions[::25], axis=1), axis=-1) for r in sources])
    spacing = np.median(edges, axis=0)
    span = float(spacing.sum())
    if span > length_m:  # markers spanning more than the rope: shrink them onto it, no tails
        spacing *= length_m / span
        span = length_m
    tail = 0.5 * (length_m - span)
    return tail + np.concatenate([[0.0], np.cumsum(spacing)]), tail


def held_nodes(
    s_nodes: np.ndarray, s_a: float, s_b: float, inner: str | None = None, snap: str = "outward"
) -> np.ndarray:
    """Node ids covering the material interval [s_a, s_b], snapped outwards to the node grid; with
    ``snap="nearest"`` the ``inner`` end ("a" or "b": the side facing the free rope) goes to the
    nearest node instead, so the clamp ends within half a node of the gripped marker rather than up
    to a node past it (``benchmarks/clamp_study.py``)."""
    dx = s_nodes[1] - s_nodes[0]
    lo = math.floor(s_a / dx + 1e-9)
    hi = math.ceil(s_b / dx - 1e-9)
    if snap not in ("outward", "nearest") or (snap == "nearest" and inner not in ("a", "b")):
        raise ValueError(f"snap 'outward', or 'nearest' with inner 'a' or 'b'; got {snap!r}, {inner!r}")
    if snap == "nearest" and inner == "b":
        hi = max(round(s_b / dx), lo + 1)
    elif snap == "nearest":
        lo = min(round(s_a / dx), hi - 1)
    return np.arange(max(lo, 0), min(hi, len(s_nodes) - 1) + 1)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def transport(d1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Parallel transport of normal(s) ``d1`` onto tangent(s) ``t`` (projection, then unit)."""
    return _unit(d1 - np.sum(d1 * t, axis=-1, keepdims=True) * t)


def _frames(t: np.ndarray, d1: np.ndarray) -> np.ndarray:
    """Director matrices (..., 3, 3), rows d1, d2 = t x d1, d3 = t (PyElastica's convention)."""
    return np.stack([d1, np.cross(t, d1), t], axis=-2)


def _curve_length(c: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(c, axis=0), axis=-1).sum())


def initial_curve(
    markers0: np.ndarray, s_markers: np.ndarray, s_nodes: np.ndarray, held_a: np.ndarray, held_b: np.ndarray
) -> np.ndarray:
    """(N, 3) node positions of the rod at the start of settling, segments all ``dx`` long.

    Held portions and tails lie on the first frame's grip lines. Between the grips: a cubic spline
    through the first frame's interior markers, tangent to the grip lines, given the rod's material
    length by adding a downward sag (if too short) or blending towards the straight chord (if too
    long), and resampled at equal arc length."""
    from scipy.interpolate import CubicSpline

    t_a = _unit(markers0[1] - markers0[0])
    u_b = _unit(markers0[-2] - markers0[-1])
    x = np.empty((len(s_nodes), 3))
    lo, hi = held_a[-1], held_b[0]
    x[: lo + 1] = markers0[0] + t_a * (s_nodes[: lo + 1] - s_markers[0])[:, None]
    x[hi:] = markers0[-1] + u_b * (s_markers[-1] - s_nodes[hi:])[:, None]
    inner = [k for k in range(len(s_markers)) if s_nodes[lo] + 1e-3 < s_markers[k] < s_nodes[hi] - 1e-3]
    pts = np.concatenate([x[lo][None], markers0[inner], x[hi][None]])
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=-1))])
    spline = CubicSpline(chord, pts, bc_type=((1, t_a), (1, -u_b)))
    u = np.linspace(0.0, chord[-1], 2001)
    base = spline(u)
    line = x[lo] + (u / chord[-1])[:, None] * (x[hi] - x[lo])
    sag = (4 * (u / chord[-1]) * (1 - u / chord[-1]))[:, None] * np.array([0.0, 0.0, -1.0])
    target = (hi - lo) * (s_nodes[1] - s_nodes[0])
    grow = _curve_length(base) < target  # too short: sag it; too long: straighten it
    shape = (lambda c: base + c * sag) if grow else (lambda c: (1 - c) * base + c * line)
    a, b = 0.0, (2.0 * target if grow else 1.0)
    for _ in range(60):  # bisection: the length is monotone in c on this bracket
        c = 0.5 * (a + b)
        if (_curve_length(shape(c)) < target) == grow:
            a = c
        else:
            b = c
    curve = shape(0.5 * (a + b))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=-1))])
    want = np.linspace(0.0, arc[-1], hi - lo + 1)
    x[lo : hi + 1] = np.stack([np.interp(want, arc, curve[:, c]) for c in range(3)], axis=1)
    return x


def driving_grips(grips: np.ndarray, lead: int = LEAD_FRAMES) -> np.ndarray:
    """The gripper trajectory (T, 4, 3) the rod is driven with, from the recorded one: the true
    grippers move smoothly, so single-frame mocap spikes (median of 5) and jitter (Gaussian, 1 frame)
    are filtered out; then ``lead`` frames are prepended in which the grippers accelerate uniformly
    from rest to their first velocity (no velocity jump when the motion starts)."""
    from scipy.ndimage import gaussian_filter1d, median_filter

    g = gaussian_filter1d(median_filter(grips, size=(5, 1, 1), mode="nearest"), 1.0, axis=0, mode="nearest")
    v0 = g[1] - g[0]  # per frame
    k = np.arange(-lead, 0, dtype=float)[:, None, None]
    before = g[0] - v0 * (-k - k**2 / (2 * lead))  # displacement of a linear velocity ramp
    return np.concatenate([before, g])
