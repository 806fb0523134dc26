"""The service's view of perception: a tracker factory, the camera built from ROS messages, and the
model state behind an estimate.

Everything here goes through perception's public names only (``Tracker``, ``Camera``).
"""

from __future__ import annotations

import numpy as np
import torch

# organize_cloud is the estimator's: it reaches perception through this module, as the rest of the service
from perception import Camera, Tracker, intrinsics_from_cloud
from perception import organize_cloud as organize_cloud
from service.geometry import pose_matrix


def make_camera(K: np.ndarray, width: int, height: int, pose: np.ndarray):
    """A perception Camera from CameraInfo's K and the camera pose (x y z qx qy qz qw, optical frame)."""
    return Camera(
        float(K[0, 0]),
        float(K[1, 1]),
        float(K[0, 2]),
        float(K[1, 2]),
        int(width),
        int(height),
        pose_matrix(np.asarray(pose, dtype=float)),
    )


def camera_frame_cloud(xyz: np.ndarray, frame: str, world: str, world_from_camera: np.ndarray) -> np.ndarray:
    """An organized cloud in the camera's optical frame, where the tracker reads it: one published in
    the world frame ``world`` (a driver's or a filter's choice; a tf name may carry a leading "/") is
    moved back with ``world_from_camera`` (4x4); one in any other frame is taken as the camera's."""
    if frame.strip("/") != world.strip("/"):
        return xyz
    T = np.asarray(world_from_camera, dtype=np.float64)
    return ((xyz - T[:3, 3]) @ T[:3, :3]).astype(np.float32)


def cloud_intrinsics(xyz: np.ndarray) -> np.ndarray | None:
    """(3, 3) K of the pinhole camera an organized camera-frame cloud was made with, None if it fits
    none (``perception.intrinsics_from_cloud``)."""
    fit = intrinsics_from_cloud(xyz)
    if fit is None:
        return None
    fx, fy, cx, cy = fit
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def make_tracker(model, **kwargs):
    """perception's Tracker for this model (perception is a dependency of the service)."""
    return Tracker(model, **kwargs)


def rod_state(tracker, model, x_prev: np.ndarray | None, x: np.ndarray):
    """The full model state behind the tracker's estimate (for prediction): the tracker's own when it
    exposes one, else rebuilt from the last two estimates."""
    state = getattr(tracker, "state", None)
    if state is not None and hasattr(state, "rest"):
        return state
    x_prev = x if x_prev is None else x_prev
    return model.initial_state(torch.tensor(x_prev)[None], torch.tensor(x)[None])
