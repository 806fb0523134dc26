"""An arm-like box placed between the camera and a chosen stretch of the rope.

The box is built in the camera frame so that its front face covers the image of the chosen arc-length
window (plus a small margin) and then extends sideways, away from the rest of the rope, like an arm
reaching in. How much of the rope it really hides is measured by the renderer's ground truth.
"""

from __future__ import annotations

import numpy as np

from perception.camera import Camera
from perception.render.mesh import box


def arc_window(curve: np.ndarray, start: float, stop: float) -> np.ndarray:
    """Points of a polyline between arc-length fractions ``start`` and ``stop`` (0..1).

    Args:
        curve: (M, 3) polyline.
        start: arc-length fraction where the window begins.
        stop: arc-length fraction where it ends.

    Returns:
        (K, 3) points.
    """
    seg = np.linalg.norm(np.diff(curve, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)]) / max(seg.sum(), 1e-12)
    keep = (s >= start) & (s <= stop)
    if keep.sum() < 2:
        i = int(np.argmin(np.abs(s - 0.5 * (start + stop))))
        keep[max(i - 1, 0) : i + 2] = True
    return curve[keep]


def occluder_box(
    curve: np.ndarray,
    window: np.ndarray,
    camera: Camera,
    radius: float,
    gap: float,
    arm_length: float = 0.5,
    thickness: float = 0.06,
) -> tuple[np.ndarray, np.ndarray]:
    """World-frame vertices and triangles of a box hiding ``window`` (K, 3) of ``curve`` (M, 3).

    Args:
        curve: (M, 3) the whole rope, world frame [m].
        window: (K, 3) the part to hide.
        camera: the camera.
        radius: rope radius [m].
        gap: distance from the rope towards the camera [m].
        arm_length: how far the box extends away from the rest of the rope [m] (like an arm).
        thickness: box depth along the optical axis [m].

    Returns:
        ``(vertices, triangles)``.
    """
    p = camera.to_camera(window)
    z_front = max(float(p[:, 2].min()) - gap, 0.3)
    q = p[:, :2] * (z_front / p[:, 2:3])
    u = q[-1] - q[0]
    if np.linalg.norm(u) < 1e-6:
        u = np.array([1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.array([-u[1], u[0]])
    a, b = q @ u, q @ w
    margin = (radius + 0.004) * z_front / float(p[:, 2].min()) + 2.0 * z_front / camera.fx
    a_lo, a_hi = a.min() - margin, a.max() + margin
    b_lo, b_hi = b.min() - margin, b.max() + margin
    rest = camera.to_camera(curve)
    rest_b = (rest[:, :2] * (z_front / rest[:, 2:3])) @ w
    if rest_b.mean() > b.mean():
        b_lo -= arm_length
    else:
        b_hi += arm_length
    centre_cam = np.array([0.0, 0.0, z_front + thickness / 2])
    centre_cam[:2] = 0.5 * (a_lo + a_hi) * u + 0.5 * (b_lo + b_hi) * w
    axes_cam = np.array([[u[0], w[0], 0.0], [u[1], w[1], 0.0], [0.0, 0.0, 1.0]])
    r = camera.world_from_camera[:3, :3]
    verts, tris = box(
        camera.to_world(centre_cam),
        r @ axes_cam,
        np.array([0.5 * (a_hi - a_lo), 0.5 * (b_hi - b_lo), thickness / 2]),
    )
    return verts, tris
