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

Segmentation and point-to-polyline distances are perception's (``segment_rope``,
``segment_distances``): the tracker and the calibration see the same rope.
"""

from __future__ import annotations

import numpy as np

from perception import Camera, segment_distances, segment_rope


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
    world = camera.to_world(segment_rope(xyz, rgb, segmentation))
    if len(world) == 0:
        return world.reshape(0, 3)
    _, first = np.unique(np.floor(world / voxel).astype(np.int64), axis=0, return_index=True)
    return world[np.sort(first)]


def polyline_distances(points: np.ndarray, x: np.ndarray) -> np.ndarray:
    r"""(N,) distance of each point to the polyline through ``x`` (n, 3): the nearest of the
    segments, :math:`\min_i |p - (x_i + t (x_{i+1} - x_i))|` with :math:`t` clamped to [0, 1]."""
    return segment_distances(points, x)


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
