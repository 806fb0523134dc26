"""Perception: occlusion-aware estimation of the rod from RGB-D clouds, on top of the DEFORM model.

API used by the service (keep it stable)::

    from perception import Tracker, Camera, render_recording
    tracker = Tracker(model, camera=None, config=None, physics=True, rest=None)
    x, observed = tracker.initialize(grip, cloud=None, camera=None)   # grip (4, 3): vertices 0, 1, n-2, n-1
    x, observed = tracker.initialize_from_frames(x0, x1)             # or from two full frames (n, 3)
    x, observed = tracker.step(grip_next)                            # every model step (model.dt)
    x, observed = tracker.correct(points_xyz, rgb, camera)           # whenever a cloud arrives

- ``model``: a :class:`deform.DeformModel` (e.g. ``deform.load_model("DLO1")``).
- ``camera``: :class:`Camera` (``fx, fy, cx, cy, width, height, world_from_camera`` 4x4); the default for
  :meth:`Tracker.correct` and :meth:`Tracker.initialize` when they get none.
- ``config``: path, dict or :class:`PerceptionConfig`; None: the defaults (listed in ``config/perception.yaml``).
- ``cloud`` for ``initialize``: ``xyz`` or ``(xyz, rgb)``. ``points_xyz``: camera-frame (H, W, 3) organized
  or (N, 3) float32, missing points NaN (or (0, 0, 0), or inf); ``rgb``: uint8 of the same leading shape, or None
  (then depth-only segmentation).
- Returns: ``x`` (n, 3) float64 world-frame vertices, never NaN; ``observed`` (n,) bool: the vertex was
  corrected from the camera in an update at most ``tracker.stale_after_s`` old. Gripped vertices are
  inputs, never corrected, and always False.
- ``step`` and ``correct`` never raise: bad clouds (empty, NaN, nothing left after filtering, wrong
  size) or failed model steps leave the tracker open-loop with vertices unobserved.
- ``physics=False``: the non-physical baseline (free vertices stay where last seen).
- ``rest``: (n-1,) edge rest lengths for ``initialize``; default from the grippers and the rod length.

``render_recording(positions, dt, fps, config, camera, seed)`` renders test clouds with ground truth.

Also public for tools built on perception (calibration, benchmarks): ``segment_rope(xyz, rgb, cfg)``
(the rope's points of a cloud, camera frame) and ``segment_distances(points, x)`` (each point's
distance to the polyline through ``x``), ``intrinsics_from_cloud(xyz)`` (the pinhole intrinsics an
organized cloud was made with), ``organize_cloud(xyz, rgb, camera)`` (an unorganized cloud on the camera's
image grid).
"""

from perception.camera import Camera, intrinsics_from_cloud, look_at
from perception.cloud import organize_cloud
from perception.config import PerceptionConfig, load_config
from perception.polyline import segment_distances
from perception.segment import segment_rope
from perception.tracker import Tracker, TrackerMoment

_RENDERER = ("RenderedFrame", "camera_steps", "default_camera", "render_recording", "rope_centreline")


def __getattr__(name: str):
    """The renderer's names load on first use: it imports open3d (1-3 s), which the tracker, and so
    the service's start-up, never needs."""
    if name in _RENDERER:
        from perception import render

        return getattr(render, name)
    raise AttributeError(f"module 'perception' has no attribute {name!r}")


__all__ = [
    "Camera",
    "PerceptionConfig",
    "RenderedFrame",
    "Tracker",
    "TrackerMoment",
    "camera_steps",
    "default_camera",
    "intrinsics_from_cloud",
    "load_config",
    "look_at",
    "organize_cloud",
    "render_recording",
    "rope_centreline",
    "segment_distances",
    "segment_rope",
]
