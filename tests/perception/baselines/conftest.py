"""Synthetic ropes for the peer trackers: a hanging curve, its nodes, and rendered-like clouds (points
on the surface of a tube around it, with noise)."""

import numpy as np

GRIP = [0, 1, 11, 12]


def rope(n: int = 13, shift=(0.0, 0.0, 0.0), bend: float = 0.0, samples: int = 400):
    """(curve points (samples, 3), nodes (n, 3)): a 0.8 m span sagging 0.3 m, evenly sampled by arc length."""
    t = np.linspace(0, 1, 2000)
    c = np.stack([0.8 * t, 0.1 * np.sin(np.pi * t) * (1 + bend), -0.3 * np.sin(np.pi * t)], 1) + np.asarray(
        shift
    )
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))]

    def at(k):
        return np.stack([np.interp(np.linspace(0, s[-1], k), s, c[:, d]) for d in range(3)], 1)

    return at(samples), at(n)


def tube(curve: np.ndarray, rng, radius: float = 0.005, per_ring: int = 6, noise: float = 0.001):
    """Points on the camera-facing half (+y) of a tube of ``radius`` around ``curve`` (K, 3), with
    Gaussian ``noise``: what a depth camera sees of a rope."""
    tangent = np.gradient(curve, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    side = np.cross(tangent, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    front = np.cross(side, tangent)
    front *= np.sign(front[:, 1:2])
    ang = np.linspace(-np.pi / 2, np.pi / 2, per_ring)
    ring = np.cos(ang)[None, :, None] * front[:, None] + np.sin(ang)[None, :, None] * side[:, None]
    pts = (curve[:, None] + radius * ring).reshape(-1, 3)
    return pts + rng.normal(0, noise, pts.shape)


def moving_rope(frames: int = 24, step=(0.003, -0.002, 0.001), turn_deg: float = 0.5):
    """Per frame (curve points, true nodes (13, 3)): the rope (of constant length) translated by
    ``step`` [m] and turned by ``turn_deg`` about the vertical through its first end, every frame
    (the far end moves 7.5 mm a frame, the near end 3.7 mm)."""
    curve, nodes = rope()
    out = []
    for f in range(1, frames + 1):
        a = np.radians(turn_deg * f)
        rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        out.append((curve @ rot.T + np.asarray(step) * f, nodes @ rot.T + np.asarray(step) * f))
    return out


def to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """(m,) distance of each point to a polyline."""
    a, e = polyline[:-1], np.diff(polyline, axis=0)
    t = np.clip(((points[:, None] - a[None]) * e[None]).sum(-1) / (e * e).sum(1)[None], 0.0, 1.0)
    return np.linalg.norm(points[:, None] - (a[None] + t[..., None] * e[None]), axis=-1).min(1)


def two_way_error(nodes: np.ndarray, curve: np.ndarray) -> float:
    """TrackDLO's error: the mean of nodes-to-true-curve and true-curve-to-node-polyline distances."""
    return 0.5 * float(to_polyline(nodes, curve).mean() + to_polyline(curve, nodes).mean())


def at_fractions(curve: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Points at arc-length ``fractions`` (0..1) of a densely sampled curve."""
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))]
    return np.stack([np.interp(np.asarray(fractions) * s[-1], s, curve[:, d]) for d in range(3)], 1)
