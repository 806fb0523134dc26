"""Pinhole depth camera: intrinsics plus pose, and the projections the tracker and renderer share.

Kept separate so the renderer, the occlusion test and the service agree on one convention:
camera frame x right, y down, z forward (OpenCV); ``world_from_camera`` maps camera to world.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Azure Kinect depth, NFOV unbinned (640x576, about 75x65 degrees); ``scaled`` gives reduced sizes.
KINECT_NFOV = dict(fx=504.0, fy=504.0, cx=320.0, cy=288.0, width=640, height=576)


@dataclass
class Camera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    world_from_camera: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self):
        self.world_from_camera = np.asarray(self.world_from_camera, dtype=np.float64).reshape(4, 4)

    @classmethod
    def kinect(cls, scale: float = 0.5, world_from_camera: np.ndarray | None = None) -> Camera:
        """Azure-Kinect-like intrinsics; ``scale=0.5`` gives 320x288 (what the tests and benchmark use)."""
        k = KINECT_NFOV
        return cls(
            k["fx"] * scale,
            k["fy"] * scale,
            k["cx"] * scale,
            k["cy"] * scale,
            round(k["width"] * scale),
            round(k["height"] * scale),
            np.eye(4) if world_from_camera is None else world_from_camera,
        )

    @property
    def camera_from_world(self) -> np.ndarray:
        return np.linalg.inv(self.world_from_camera)

    @property
    def position(self) -> np.ndarray:
        return self.world_from_camera[:3, 3].copy()

    def to_camera(self, p_world: np.ndarray) -> np.ndarray:
        r, t = self.world_from_camera[:3, :3], self.world_from_camera[:3, 3]
        return (np.asarray(p_world, dtype=np.float64) - t) @ r

    def to_world(self, p_cam: np.ndarray) -> np.ndarray:
        r, t = self.world_from_camera[:3, :3], self.world_from_camera[:3, 3]
        return np.asarray(p_cam, dtype=np.float64) @ r.T + t

    def project(self, p_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) (column u, row v) and depth (...) of camera-frame points."""
        p = np.asarray(p_cam, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * p[..., 0] / z + self.cx
            v = self.fy * p[..., 1] / z + self.cy
        return np.stack([u, v], axis=-1), z

    def ray_directions(self) -> np.ndarray:
        """(H, W, 3) camera-frame rays through pixel centres with z = 1 (so ray length = depth)."""
        u, v = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)


MIN_FIT_PIXELS = 100  # measured pixels an intrinsics fit needs
FIT_PIXELS = 20_000  # pixels an intrinsics fit reads at most (every k-th row and column)


def intrinsics_from_cloud(
    xyz: np.ndarray, max_error_px: float = 1.0
) -> tuple[float, float, float, float] | None:
    r"""The pinhole intrinsics an organized cloud was made with: pixel (row :math:`i`, column :math:`j`)
    holds the point its ray met, so :math:`j + \tfrac12 = f_x x / z + c_x` and
    :math:`i + \tfrac12 = f_y y / z + c_y` (the pixel-centre convention of :meth:`Camera.project`).
    Least squares over the measured pixels: the cloud is its own calibration when its camera info is
    missing or of another image size.

    Args:
        xyz: (H, W, 3) camera-frame organized cloud [m]; missing points NaN, zero or inf.
        max_error_px: the largest median reprojection error accepted [pixels].

    Returns:
        ``(fx, fy, cx, cy)``, or None with fewer than ``MIN_FIT_PIXELS`` measured pixels or a median
        error above ``max_error_px`` (not one pinhole camera's cloud).
    """
    p = np.asarray(xyz)
    if p.ndim != 3 or p.shape[-1] != 3:
        return None
    step = max(1, int(np.sqrt(p.shape[0] * p.shape[1] / FIT_PIXELS)))  # a grid of pixels suffices
    rows, cols = (step * i for i in np.indices(p[::step, ::step].shape[:2]))
    p = p[::step, ::step].astype(np.float64)
    z = p[..., 2]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(p).all(-1) & (z > 0)
    if ok.sum() < MIN_FIT_PIXELS:
        return None
    out, errors = [], []
    for k, pixel in ((0, cols), (1, rows)):
        ratio, centre = p[..., k][ok] / z[ok], pixel[ok] + 0.5
        if np.ptp(ratio) <= 0:
            return None
        A = np.stack([ratio, np.ones_like(ratio)], axis=1)
        (f, c), *_ = np.linalg.lstsq(A, centre, rcond=None)
        out += [f, c]
        errors.append(np.abs(A @ (f, c) - centre))
    if out[0] <= 0 or out[2] <= 0 or np.median(np.concatenate(errors)) > max_error_px:
        return None
    return float(out[0]), float(out[2]), float(out[1]), float(out[3])


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """world_from_camera of a camera at ``eye`` looking at ``target`` (image up close to ``up``).

    Args:
        eye: (3,) camera position, world frame [m].
        target: (3,) point looked at [m].
        up: (3,) the world direction that should point up in the image.

    Returns:
        (4, 4) world_from_camera (optical frame: z forward, y down).
    """
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose
