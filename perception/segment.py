"""Rope points of an RGB-D cloud: finite, inside the depth range, and (when colour is given) of the rope's hue.

Colour comes first because it is what separates a thin rope from the table it hangs above;
without colour only the depth range applies and the distance filter of the estimator does the rest.
"""
from __future__ import annotations

import cv2
import numpy as np

from perception.config import SegmentationConfig


def colour_mask(rgb: np.ndarray, cfg: SegmentationConfig) -> np.ndarray:
    """(N,) bool: pixels whose OpenCV HSV lies within the thresholds (hue may wrap around 180)."""
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb.reshape(-1, 1, 3), dtype=np.uint8), cv2.COLOR_RGB2HSV).reshape(-1, 3)
    lo, hi = np.asarray(cfg.hsv_low), np.asarray(cfg.hsv_high)
    sv = np.all((hsv[:, 1:] >= lo[1:]) & (hsv[:, 1:] <= hi[1:]), axis=1)
    h = hsv[:, 0]
    hue = (h >= lo[0]) & (h <= hi[0]) if lo[0] <= hi[0] else (h >= lo[0]) | (h <= hi[0])
    return sv & hue


def segment_rope(xyz: np.ndarray, rgb: np.ndarray | None, cfg: SegmentationConfig) -> np.ndarray:
    """(N, 3) float64 camera-frame rope points from an organized (H, W, 3) or flat (N, 3) cloud.

    ``rgb`` of another shape than ``xyz`` is ignored (depth-only segmentation)."""
    pts = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    keep = np.all(np.isfinite(pts), axis=1)
    z = np.where(keep, pts[:, 2], -1.0)
    keep &= (z >= cfg.depth_min) & (z <= cfg.depth_max)
    if rgb is not None:
        colours = np.asarray(rgb)
        if colours.size == pts.size:
            keep &= colour_mask(colours.reshape(-1, 3), cfg)
    return pts[keep]
