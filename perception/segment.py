"""Rope points of an RGB-D cloud: finite, inside the depth range, (when colour is given) of the rope's
hue, and (in an organized cloud) on the rope's front surface.

Colour comes first because it is what separates a thin rope from the table it hangs above;
without colour only the depth range applies and the distance filter of the estimator does the rest.

Real sensors put the rope's colour where the rope is not: the colour camera is registered to the
depth camera within a few pixels, so the rope's hue lands on the table beside and behind it, and
depth edges give mixed pixels between the rope and what lies behind it. Those points sit well
behind the rope's own pixels next to them (:func:`front_surface`); a tracker that took them for
rope would see a rope smeared towards the background, and so much unexplained rope that it would
count the rope as lost.
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
    # one row of N pixels: as an (N, 1) column OpenCV converts row by row, 7x slower
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb.reshape(1, -1, 3), dtype=np.uint8), cv2.COLOR_RGB2HSV)
    lo, hi = [int(v) for v in cfg.hsv_low], [int(v) for v in cfg.hsv_high]
    if lo[0] <= hi[0]:
        mask = cv2.inRange(hsv, np.array(lo, np.uint8), np.array(hi, np.uint8))
    else:  # hue range wraps (reds)
        mask = cv2.inRange(hsv, np.array(lo, np.uint8), np.array([180, hi[1], hi[2]], np.uint8))
        mask |= cv2.inRange(hsv, np.array([0, lo[1], lo[2]], np.uint8), np.array(hi, np.uint8))
    return mask.reshape(-1) > 0


def front_surface(z: np.ndarray, mask: np.ndarray, window: int, margin: float) -> np.ndarray:
    """(H, W) bool: the pixels of ``mask`` no more than ``margin`` behind the nearest masked pixel
    within ``window`` pixels (a (2 window + 1)^2 square): the rope's own surface, not its colour
    spilled onto what lies behind it.

    Args:
        z: (H, W) depth along the optical axis [m]; unknown as NaN, zero or inf (a zero taken for
            depth would be rope at the lens, in front of every rope pixel around it).
        mask: (H, W) bool, the rope-coloured pixels.
        window: half size of the window [pixels].
        margin: how far behind the nearest rope pixel a rope pixel may lie [m].

    Returns:
        (H, W) bool, a subset of ``mask``.
    """
    with np.errstate(invalid="ignore"):
        ok = mask & (z > 0) & (z < np.inf)
    rows, cols = np.flatnonzero(ok.any(1)), np.flatnonzero(ok.any(0))
    if not len(rows):
        return ok
    box = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]  # only the rope's part of the image
    near = np.where(ok[box], z[box], np.inf).astype(np.float32)
    kernel = np.ones((2 * window + 1, 2 * window + 1), np.uint8)
    front = cv2.erode(near, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=float("inf"))
    out = np.zeros_like(ok)
    with np.errstate(invalid="ignore"):
        out[box] = ok[box] & (z[box] <= front + margin)
    return out


def segment_rope(xyz: np.ndarray, rgb: np.ndarray | None, cfg: SegmentationConfig) -> np.ndarray:
    """(N, 3) float64 camera-frame rope points from an organized (H, W, 3) or flat (N, 3) cloud.

    ``rgb`` of another shape than ``xyz`` is ignored (depth-only segmentation).

    Args:
        xyz: camera-frame points, (H, W, 3) or (N, 3); missing as NaN, zero or inf
            (:func:`perception.cloud.measured_depth`).
        rgb: uint8 colours of the same leading shape, or None.
        cfg: the segmentation settings (HSV thresholds, depth range, front-surface filter).

    Returns:
        (N, 3).
    """
    arr = np.asarray(xyz)
    pts = arr.reshape(-1, 3)
    keep = np.ones(len(pts), dtype=bool)
    if rgb is not None and np.asarray(rgb).size == pts.size:
        keep = colour_mask(np.asarray(rgb).reshape(-1, 3), cfg)
        if arr.ndim == 3 and cfg.spill_window > 0:
            z = arr[..., 2].astype(np.float64)
            keep = front_surface(z, keep.reshape(z.shape), cfg.spill_window, cfg.spill_margin).reshape(-1)
    pts = pts[keep].astype(np.float64)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(pts.sum(1)) & (pts[:, 2] >= cfg.depth_min) & (pts[:, 2] <= cfg.depth_max)
    return pts[keep]
