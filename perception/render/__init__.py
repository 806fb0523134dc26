"""Synthetic RGB-D clouds of a rod trajectory, as a depth camera would see them (see :func:`render_recording`).

Used to test and benchmark the tracker against known ground truth, with occlusions of a chosen size.
"""

from __future__ import annotations

import math

import numpy as np

from perception.camera import Camera, look_at
from perception.config import PerceptionConfig, RenderConfig, load_config
from perception.render.mesh import catmull_rom
from perception.render.occluder import arc_window, occluder_box
from perception.render.scene import RenderedFrame, render_frame

__all__ = [
    "RenderedFrame",
    "blacked_out",
    "camera_steps",
    "default_camera",
    "render_recording",
    "rope_centreline",
]


def rope_centreline(x: np.ndarray, samples_per_segment: int = 8) -> np.ndarray:
    """(M, 3) the rope's centreline as the renderer draws it: a smooth curve through the vertices
    ``x`` (n, 3), vertex j at point ``j * samples_per_segment``. A real rope bends smoothly between
    its markers; what a camera shows is this curve, not the marker polyline."""
    return catmull_rom(x, samples_per_segment)


def default_camera(positions: np.ndarray, cfg: RenderConfig) -> Camera:
    """A Kinect-like camera in front of the workspace, looking down at ``camera_elevation_deg``,
    perpendicular to the gripper-to-gripper direction of the first frame, turned
    ``camera_azimuth_deg`` about the vertical from there.

    Args:
        positions: (T, n, 3) the motion to film [m].
        cfg: the render settings.

    Returns:
        A :class:`perception.camera.Camera`.
    """
    p = np.asarray(positions, dtype=np.float64).reshape(-1, positions.shape[-2], 3)
    centre = 0.5 * (p.reshape(-1, 3).min(0) + p.reshape(-1, 3).max(0))
    span = p[0, -1] - p[0, 0]
    span[2] = 0.0
    side = np.array([1.0, 0.0, 0.0]) if np.linalg.norm(span) < 1e-6 else span / np.linalg.norm(span)
    toward = np.cross(np.array([0.0, 0.0, 1.0]), side)  # horizontal, perpendicular to the rope plane
    if cfg.camera_azimuth_deg:
        az = math.radians(cfg.camera_azimuth_deg)
        toward = math.cos(az) * toward + math.sin(az) * side
    el = math.radians(cfg.camera_elevation_deg)
    eye = centre + cfg.camera_distance * (math.cos(el) * toward + math.sin(el) * np.array([0.0, 0.0, 1.0]))
    return Camera.kinect(cfg.scale, look_at(eye, centre))


def camera_steps(n_steps: int, dt: float, fps: float) -> list[int]:
    """Trajectory indices at which a camera running at ``fps`` delivers a frame (starting at 0).

    Args:
        n_steps: trajectory steps.
        dt: seconds per step.
        fps: camera frame rate.

    Returns:
        Step indices.
    """
    if fps <= 0:
        return []
    k = np.arange(0, int(n_steps * dt * fps) + 1)
    steps = np.unique(np.round(k / (fps * dt)).astype(int))
    return [int(s) for s in steps if s < n_steps]


def blacked_out(t: float, cfg: RenderConfig) -> bool:
    """True when the whole rope is hidden at time ``t`` [s] (``blackout_start_s <= t <
    blackout_start_s + blackout_s``).

    Args:
        t: time into the recording [s].
        cfg: the render settings.

    Returns:
        bool.
    """
    return cfg.blackout_s > 0 and cfg.blackout_start_s <= t < cfg.blackout_start_s + cfg.blackout_s - 1e-9


def render_recording(
    positions: np.ndarray,
    dt: float = 0.01,
    fps: float = 30.0,
    config=None,
    camera: Camera | None = None,
    seed: int = 0,
    steps=None,
    obstacles=(),
) -> list[RenderedFrame]:
    """Render a trajectory ``positions`` (T, n, 3) (world, metres) at ``fps`` (or at given ``steps``).

    With ``occlusion > 0`` an occluder hides about that fraction of the free rope between
    ``occlusion_start`` and ``occlusion_end`` (fractions of the recording). With ``blackout_s > 0`` an
    occluder hides the whole rope (and the grippers) from ``blackout_start_s`` for ``blackout_s``
    seconds: the rope is out of sight, as when a person walks between camera and rope. The table is
    drawn at ``table_z``; ``obstacles`` are fixed meshes in the scene (e.g. a post the rope catches on).

    Args:
        positions: (T, n, 3) world-frame vertices [m], one per model step.
        dt: seconds per model step.
        fps: camera frame rate (ignored when ``steps`` is given).
        config: a :class:`RenderConfig`, a :class:`PerceptionConfig` or anything :func:`load_config` takes.
        camera: the camera (default: :func:`default_camera` looking at the motion).
        seed: depth noise, dropouts and colour noise.
        steps: the model steps to render (default every ``1 / fps`` seconds).
        obstacles: fixed world-frame ``(vertices, triangles)`` meshes drawn in the scene (they hide
            what is behind them and are not rope-coloured); e.g. :func:`perception.render.mesh.cylinder`.

    Returns:
        One :class:`RenderedFrame` per rendered step: organised camera-frame points (H, W, 3) float32
        with NaN where depth is missing, colours (H, W, 3) uint8, the camera and the true vertices.
    """
    if isinstance(config, RenderConfig):
        cfg = config
    else:
        cfg = (config if isinstance(config, PerceptionConfig) else load_config(config)).render
    positions = np.asarray(positions, dtype=np.float64)
    n_steps = len(positions)
    camera = camera or default_camera(positions, cfg)
    steps = camera_steps(n_steps, dt, fps) if steps is None else list(steps)
    rng = np.random.default_rng(seed)
    f = float(np.clip(cfg.occlusion, 0.0, 0.95))
    centre0 = rng.uniform(f / 2 + 0.05, 1 - f / 2 - 0.05) if f > 0 else 0.5
    drift_hz = rng.uniform(0.1, 0.3)
    frames = []
    for s in steps:
        x = positions[s]
        occluder = None
        phase = s / max(n_steps - 1, 1)
        active = f > 0 and cfg.occlusion_start <= phase <= cfg.occlusion_end
        if blacked_out(s * dt, cfg):
            curve = catmull_rom(x)
            occluder = occluder_box(curve, curve, camera, cfg.rope_radius, cfg.occluder_gap)
            active = True
        elif active:
            n = len(x)
            free = catmull_rom(x[1 : n - 1])
            c = centre0 + 0.04 * math.sin(2 * math.pi * drift_hz * s * dt)
            window = arc_window(free, c - f / 2, c + f / 2)
            occluder = occluder_box(catmull_rom(x), window, camera, cfg.rope_radius, cfg.occluder_gap)
        xyz, rgb, visible = render_frame(x, camera, cfg, rng, occluder, obstacles)
        frames.append(RenderedFrame(xyz, rgb, camera, visible, int(s), active))
    return frames
