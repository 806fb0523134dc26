r"""The rope as the camera sees it, independent of any model: the fixed reference every calibration
score is measured against (tracks and models change from round to round, the clouds do not).

- :func:`rope_points`: the cloud's points in the rope's colour range and depth range, in the world
  frame, on a voxel grid (one point per cell, so that near parts of the rope do not outweigh far ones).
- :func:`polyline_distances`: distance of each point to the polyline through a rod's vertices.
- :func:`reach_bound`: a lower bound on the rope length between the grippers. A point ``p`` on the
  rope at arc length ``s`` from the first inner gripped vertex ``g_1`` satisfies
  :math:`|p - g_1| \le s` and :math:`|p - g_2| \le L_{free} - s`, so
  :math:`|p - g_1| + |p - g_2| \le L_{free}` for every rope point: the largest sum seen bounds the
  free length from below, whatever hides the rest of the rope.

The colour test repeats :func:`perception.segment` 's rule (OpenCV HSV thresholds, hue wrapping
past 180) with the same settings: perception does not export its segmentation, and calibration must
not reach into perception's internals.
"""

from __future__ import annotations

import cv2
import numpy as np

from perception import Camera


def colour_mask(rgb: np.ndarray, hsv_low, hsv_high) -> np.ndarray:
    """(N,) bool: colours whose OpenCV HSV lies in ``[hsv_low, hsv_high]`` (H in 0..180; a low hue
    above the high one wraps through red).

    Args:
        rgb: (N, 3) uint8.
        hsv_low: (3,) lower bounds.
        hsv_high: (3,) upper bounds.

    Returns:
        (N,) bool.
    """
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb.reshape(-1, 1, 3), dtype=np.uint8), cv2.COLOR_RGB2HSV)
    lo, hi = [int(v) for v in hsv_low], [int(v) for v in hsv_high]
    if lo[0] <= hi[0]:
        mask = cv2.inRange(hsv, np.array(lo, np.uint8), np.array(hi, np.uint8))
    else:
        mask = cv2.inRange(hsv, np.array(lo, np.uint8), np.array([180, hi[1], hi[2]], np.uint8))
        mask |= cv2.inRange(hsv, np.array([0, lo[1], lo[2]], np.uint8), np.array(hi, np.uint8))
    return mask.reshape(-1) > 0


def rope_points(
    xyz: np.ndarray, rgb: np.ndarray, camera: Camera, segmentation, voxel: float = 0.01
) -> np.ndarray:
    """(N, 3) world-frame rope points of a cloud, one per ``voxel`` cell.

    Args:
        xyz: (H, W, 3) camera-frame points [m], NaN where missing.
        rgb: (H, W, 3) uint8.
        camera: the cloud's camera.
        segmentation: perception's segmentation settings (``hsv_low``, ``hsv_high``, ``depth_min``,
            ``depth_max``).
        voxel: grid cell [m].

    Returns:
        (N, 3) float64.
    """
    pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    pts = pts[colour_mask(np.asarray(rgb).reshape(-1, 3), segmentation.hsv_low, segmentation.hsv_high)]
    with np.errstate(invalid="ignore"):
        keep = (
            np.isfinite(pts).all(1)
            & (pts[:, 2] >= segmentation.depth_min)
            & (pts[:, 2] <= segmentation.depth_max)
        )
    world = camera.to_world(pts[keep])
    if len(world) == 0:
        return world.reshape(0, 3)
    _, first = np.unique(np.floor(world / voxel).astype(np.int64), axis=0, return_index=True)
    return world[np.sort(first)]


def polyline_distances(points: np.ndarray, x: np.ndarray) -> np.ndarray:
    r"""(N,) distance of each point to the polyline through ``x`` (n, 3): the nearest of the
    segments, :math:`\min_i |p - (x_i + t (x_{i+1} - x_i))|` with :math:`t` clamped to [0, 1]."""
    a, e = x[:-1], np.diff(x, axis=0)
    t = np.einsum("nij,ij->ni", points[:, None, :] - a[None], e) / np.maximum((e * e).sum(1), 1e-12)
    near = a[None] + np.clip(t, 0.0, 1.0)[..., None] * e[None]
    return np.linalg.norm(points[:, None, :] - near, axis=-1).min(1)


def reach_bound(points: np.ndarray, grip: np.ndarray, quantile: float = 0.98) -> float:
    """A lower bound on the free rope length (between vertices 1 and n-2) from one cloud: the
    ``quantile`` of :math:`|p - g_1| + |p - g_2|` over the rope points (a high quantile, not the
    maximum, so that a few stray rope-coloured returns do not count).

    Args:
        points: (N, 3) rope points, world frame [m], N > 0.
        grip: (4, 3) gripped vertices 0, 1, n-2, n-1 [m].
        quantile: in (0, 1].

    Returns:
        Metres.
    """
    s = np.linalg.norm(points - grip[1], axis=1) + np.linalg.norm(points - grip[2], axis=1)
    return float(np.quantile(s, quantile))
