"""Cloud utilities the estimator needs: voxel-grid downsampling, a depth image for occlusion tests,
and unorganized clouds put back on the camera's image grid.

A depth image is what the occlusion test compares predicted vertex depths against; flat clouds (or
organized clouds of the wrong size) are projected into one with a z-buffer.

Cameras and drivers mark a pixel without a measurement differently: NaN (the Azure Kinect driver,
``depth_image_proc``), ``(0, 0, 0)`` (RealSense's ordered clouds, a renderer that leaves the empty
background at zero depth), +-inf (out of range). :func:`measured_depth` reads them all as missing:
a zero read as depth would be a wall at the lens, hiding the whole rope behind it.
"""

from __future__ import annotations

import numpy as np

from perception.camera import Camera


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Centroids of the occupied cells of a ``voxel``-sized grid (keeps ~uniform density for the GMM).

    Args:
        points: (N, 3) points [m].
        voxel: cell size [m].

    Returns:
        (M, 3) centroids, M <= N.
    """
    if len(points) == 0 or voxel <= 0:
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(0)
    dims = keys.max(0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    out = np.zeros((len(counts), 3))
    np.add.at(out, inverse, points)
    return out / counts[:, None]


def measured_depth(xyz: np.ndarray) -> np.ndarray:
    """Depth along the optical axis of camera-frame points, NaN where nothing was measured (a
    measurement lies in front of the camera: z finite and > 0; NaN, zero and +-inf are missing).

    Args:
        xyz: (..., 3) camera-frame points [m].

    Returns:
        (...) depth [m], float of the input's precision.
    """
    z = np.asarray(xyz)[..., 2]
    with np.errstate(invalid="ignore"):
        return np.where((z > 0) & (z < np.inf), z, np.nan)


MIN_NOISE_PIXELS = 100  # second differences a noise estimate needs


def depth_noise(depth: np.ndarray, near: float, far: float, row_step: int = 4) -> float:
    r"""The camera's depth noise :math:`\sigma` [m] among the pixels of an organized depth image whose
    depth lies within ``[near, far]`` (the noise grows with depth: the rope's, not the far wall's).

    From the second differences along rows, :math:`e_j = z_{j-1} - 2 z_j + z_{j+1}`: on a surface
    smooth at the pixel scale they vanish, and independent per-pixel noise gives them the variance
    :math:`6 \sigma^2`. Depth edges are outliers, so the spread is taken robustly:
    :math:`\sigma = 1.4826 \, \mathrm{median} |e| / \sqrt 6`.

    Args:
        depth: (H, W) depth along the optical axis [m], NaN or inf where unknown.
        near, far: the depths to measure at [m].
        row_step: every how many rows (the estimate needs far fewer than an image has).

    Returns:
        sigma [m]; 0 with fewer than ``MIN_NOISE_PIXELS`` usable pixels (a sparse or flat cloud).
    """
    z = np.asarray(depth, dtype=np.float64)[::row_step]
    if z.ndim != 2 or z.shape[1] < 3:
        return 0.0
    e = z[:, :-2] - 2.0 * z[:, 1:-1] + z[:, 2:]
    mid = z[:, 1:-1]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(e) & (mid >= near) & (mid <= far)
    if ok.sum() < MIN_NOISE_PIXELS:
        return 0.0
    return float(1.4826 * np.median(np.abs(e[ok])) / np.sqrt(6.0))


def decimate(xyz: np.ndarray, rgb: np.ndarray | None, max_points: int):
    """Keep every s-th row and column of an organized cloud (every s^2-th point of a flat one) so that
    at most about ``max_points`` remain (a guard for clouds far beyond an RGB-D camera's depth
    resolution: a stride drops most of a rope that is a line one or two pixels wide).

    Args:
        xyz: (H, W, 3) organized or (N, 3) points.
        rgb: colours of the same leading shape, or None (dropped if the shape differs).
        max_points: the budget (0 or less: keep all).

    Returns:
        ``(xyz, rgb)`` decimated the same way.
    """
    xyz = np.asarray(xyz)
    count = int(np.prod(xyz.shape[:-1])) if xyz.ndim >= 2 else 0
    if max_points <= 0 or count <= max_points:
        return xyz, rgb
    s = int(np.ceil(np.sqrt(count / max_points)))
    same = rgb is not None and np.asarray(rgb).shape[:-1] == xyz.shape[:-1]
    if xyz.ndim == 3:
        return xyz[::s, ::s], (np.asarray(rgb)[::s, ::s] if same else None)
    return xyz[:: s * s], (np.asarray(rgb)[:: s * s] if same else None)


def depth_image(xyz: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) depth (NaN where unknown) of a camera-frame cloud, organized or not.

    Args:
        xyz: camera-frame points, (H, W, 3) organized for this camera, or (N, 3).
        camera: the camera that took them.

    Returns:
        (H, W) depth along the optical axis [m].
    """
    arr = np.asarray(xyz)
    if arr.shape == (camera.height, camera.width, 3):
        return measured_depth(arr)
    pts = arr.reshape(-1, 3).astype(np.float64)
    pts = pts[np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0)]
    depth = np.full((camera.height, camera.width), np.inf)
    if len(pts):
        uv, z = camera.project(pts)
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        np.minimum.at(depth, (v[ok], u[ok]), z[ok])
    depth[np.isinf(depth)] = np.nan
    return depth


def organize_cloud(xyz: np.ndarray, rgb: np.ndarray | None, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """An unorganized camera-frame cloud on the camera's image grid: each point in the pixel it
    projects to, the nearest where several do, NaN (black) where none does.

    Why: drivers publish clouds without their grid too (RealSense's ``pointcloud`` filter drops the
    pixels without depth and sends the rest as one row, ``create_cloud`` makes one from a list of
    points), and the tracker reasons about occlusion, the rope's front surface and depth noise on the
    image grid. A cloud made from this camera's pixels comes back as it was made: pixel (i, j) holds
    the point whose ray passes through its centre (:meth:`Camera.project`).

    Args:
        xyz: (..., 3) camera-frame points [m]; missing points NaN, zero or inf are dropped.
        rgb: (..., 3) uint8 colours of the same leading shape, or None.
        camera: the camera whose grid the points are put on (its intrinsics and image size).

    Returns:
        ``(xyz (H, W, 3) float32, rgb (H, W, 3) uint8)``.
    """
    pts = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    col = (
        np.zeros(pts.shape, dtype=np.uint8) if rgb is None else np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
    )
    H, W = camera.height, camera.width
    out_xyz = np.full((H, W, 3), np.nan, dtype=np.float32)
    out_rgb = np.zeros((H, W, 3), dtype=np.uint8)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        z = pts[:, 2]
        u = np.floor(camera.fx * pts[:, 0] / z + camera.cx)
        v = np.floor(camera.fy * pts[:, 1] / z + camera.cy)
        # (NaN and inf fail every comparison; a point at or behind the lens is no measurement)
        idx = np.flatnonzero((z > 0) & (z < np.inf) & (u >= 0) & (u < W) & (v >= 0) & (v < H))
    pixel = (v[idx] * W + u[idx]).astype(np.int64)
    shared = np.bincount(pixel, minlength=H * W)[pixel] > 1
    if shared.any():  # several points in one pixel (another camera's cloud, merged clouds): the nearest
        nearest = np.full(H * W, np.inf, dtype=z.dtype)
        np.minimum.at(nearest, pixel[shared], z[idx[shared]])
        keep = ~shared | (z[idx] == nearest[pixel])  # (a tie keeps either: both are as near)
        idx, pixel = idx[keep], pixel[keep]
    # rows copied as one 12-byte (3-byte) item each: a third of the time of three floats
    out_xyz.reshape(-1).view(np.dtype((np.void, 12)))[pixel] = np.ascontiguousarray(pts).view(
        np.dtype((np.void, 12))
    )[idx, 0]
    out_rgb.reshape(-1).view(np.dtype((np.void, 3)))[pixel] = np.ascontiguousarray(col).view(
        np.dtype((np.void, 3))
    )[idx, 0]
    return out_xyz, out_rgb


def window_min(depth: np.ndarray, uv: np.ndarray, half: int) -> np.ndarray:
    """Smallest known depth in a (2 half + 1)^2 window around each pixel ``uv`` (NaN if none/outside).

    Args:
        depth: (H, W) depth image [m], NaN where unknown.
        uv: (K, 2) integer pixel coordinates (column, row).
        half: half size of the window [pixels].

    Returns:
        (K,) depths [m].
    """
    h, w = depth.shape
    out = np.full(len(uv), np.nan)
    for i, (u, v) in enumerate(uv):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        c, r = int(np.floor(u)), int(np.floor(v))
        if c < 0 or c >= w or r < 0 or r >= h:
            continue
        patch = depth[max(r - half, 0) : r + half + 1, max(c - half, 0) : c + half + 1]
        if np.isfinite(patch).any():
            out[i] = np.nanmin(patch)
    return out
