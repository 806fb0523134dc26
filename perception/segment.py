"""Rope points of an RGB-D cloud: finite, inside the depth range, and (when colour is given) of the rope's hue.

Colour comes first because it is what separates a thin rope from the table it hangs above;
without colour only the depth range applies and the distance filter of the estimator does the rest.
"""

from __future__ import annotations

import cv2
import numpy as np

from perception.config import SegmentationConfig


def colour_mask(rgb: np.ndarray, cfg: SegmentationConfig) -> np.ndarray:
    """(N,) bool: pixels whose OpenCV HSV lies within the thresholds (hue may wrap around 180).

    Args:
        rgb: (N, 3) uint8 colours.
        cfg: the HSV thresholds.

    Returns:
        (N,) bool.
    """
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb.reshape(-1, 1, 3), dtype=np.uint8), cv2.COLOR_RGB2HSV)
    lo, hi = [int(v) for v in cfg.hsv_low], [int(v) for v in cfg.hsv_high]
    if lo[0] <= hi[0]:
        mask = cv2.inRange(hsv, np.array(lo, np.uint8), np.array(hi, np.uint8))
    else:  # hue range wraps (reds)
        mask = cv2.inRange(hsv, np.array(lo, np.uint8), np.array([180, hi[1], hi[2]], np.uint8))
        mask |= cv2.inRange(hsv, np.array([0, lo[1], lo[2]], np.uint8), np.array(hi, np.uint8))
    return mask.reshape(-1) > 0


def segment_rope(xyz: np.ndarray, rgb: np.ndarray | None, cfg: SegmentationConfig) -> np.ndarray:
    """(N, 3) float64 camera-frame rope points from an organized (H, W, 3) or flat (N, 3) cloud.

    ``rgb`` of another shape than ``xyz`` is ignored (depth-only segmentation).

    Args:
        xyz: camera-frame points, (H, W, 3) or (N, 3), NaN where missing.
        rgb: uint8 colours of the same leading shape, or None.
        cfg: the segmentation settings (HSV thresholds, depth range).

    Returns:
        (N, 3).
    """
    pts = np.asarray(xyz).reshape(-1, 3)
    if rgb is not None and np.asarray(rgb).size == pts.size:
        pts = pts[colour_mask(np.asarray(rgb).reshape(-1, 3), cfg)]
    pts = pts.astype(np.float64)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(pts.sum(1)) & (pts[:, 2] >= cfg.depth_min) & (pts[:, 2] <= cfg.depth_max)
    return pts[keep]
