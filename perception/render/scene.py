"""Render one organized RGB-D cloud of the rope scene with open3d's CPU raycaster (no window, no GPU).

Sensor effects that matter for the tracker are imitated: depth noise growing with distance,
missing pixels on the far side of depth edges (and some on the near side), random dropouts,
shading and colour noise; optionally (off by default) mixed depth pixels at edges and a colour
image registered a few pixels off the depth. Ground-truth visibility of each vertex comes from a
ray to its centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

import perception.render.mesh as mesh
from perception.camera import Camera
from perception.config import RenderConfig

ROPE, TABLE, GRIPPER, OCCLUDER = 0, 1, 2, 3
NOTHING_RGB = 40.0  # what the colour camera sees where no surface is in range (a dark room)


@dataclass
class RenderedFrame:
    """``xyz`` (H, W, 3) float32 camera frame (NaN = no data), ``rgb`` (H, W, 3) uint8,
    ``visible`` (n,) ground-truth visibility of the vertices, ``step`` index in the trajectory."""

    xyz: np.ndarray
    rgb: np.ndarray
    camera: Camera
    visible: np.ndarray
    step: int
    occluded: bool = False


def scene_meshes(x: np.ndarray, cfg: RenderConfig, occluder=None, obstacles=()):
    """Vertices, triangles and a per-triangle label of the rope, table, grippers (and occluder, obstacles).

    Args:
        x: (n, 3) rod vertices, world frame [m].
        cfg: the render settings.
        occluder: ``(vertices, triangles)`` of an occluder, or None.
        obstacles: ``(vertices, triangles)`` of fixed world-frame meshes (e.g. a post), drawn in the
            occluder's colour.

    Returns:
        ``(vertices (V, 3), triangles (T, 3), labels (T,))``.
    """
    n = len(x)
    parts = [
        (mesh.tube(mesh.catmull_rom(x), cfg.rope_radius), ROPE),
        (mesh.plane(cfg.table_z, centre=x[:, :2].mean(0)), TABLE),
    ]
    for a, b in ((0, 1), (n - 1, n - 2)):
        axis = x[b] - x[a]
        half = np.array([0.5 * np.linalg.norm(axis) + 0.015, 0.025, 0.03])
        parts.append((mesh.box(0.5 * (x[a] + x[b]), mesh.frame_from_axis(axis), half), GRIPPER))
    if occluder is not None:
        parts.append((occluder, OCCLUDER))
    parts.extend((ob, OCCLUDER) for ob in obstacles or ())
    verts, tris, labels, offset = [], [], [], 0
    for (v, t), lab in parts:
        verts.append(v)
        tris.append(t + offset)
        labels.append(np.full(len(t), lab))
        offset += len(v)
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(labels)


def _raycast(verts, tris, origins, dirs):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32)))
    rays = np.concatenate([origins, dirs], axis=-1).astype(np.float32)
    out = scene.cast_rays(o3d.core.Tensor(rays))
    return out["t_hit"].numpy(), out["primitive_ids"].numpy(), out["primitive_normals"].numpy()


def vertex_visibility(x: np.ndarray, camera: Camera, verts, tris, labels, radius: float) -> np.ndarray:
    """True where the first thing on the ray to the vertex centre is the rope, near the vertex.

    Args:
        x: (n, 3) rod vertices, world frame [m].
        camera: the camera.
        verts: (V, 3) scene vertices.
        tris: (T, 3) triangles.
        labels: (T,) labels.
        radius: rope radius [m].

    Returns:
        (n,) bool.
    """
    eye = camera.position
    d = x - eye
    dist = np.linalg.norm(d, axis=1)
    t, prim, _ = _raycast(verts, tris, np.broadcast_to(eye, d.shape), d / dist[:, None])
    hit_rope = np.isfinite(t) & (prim != o3d.t.geometry.RaycastingScene.INVALID_ID)
    hit_rope &= labels[np.where(hit_rope, prim, 0)] == ROPE
    uv, z = camera.project(camera.to_camera(x))
    inside = (
        (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    )
    return hit_rope & (t > dist - 3 * radius) & inside


def render_frame(
    x: np.ndarray, camera: Camera, cfg: RenderConfig, rng: np.random.Generator, occluder=None, obstacles=()
):
    """(xyz, rgb, visible) of the scene with rod vertices ``x`` (n, 3) in the world frame.

    Args:
        x: (n, 3) rod vertices, world frame [m].
        camera: the camera.
        cfg: the render settings (noise, colours, edge and dropout model).
        rng: the random generator.
        occluder: ``(vertices, triangles)`` or None.
        obstacles: fixed world-frame ``(vertices, triangles)`` meshes (see :func:`scene_meshes`).

    Returns:
        ``(xyz, rgb, visible)``: xyz (H, W, 3) float32 camera frame with NaN where no depth, rgb
        (H, W, 3) uint8, visible (n,) bool.
    """
    verts, tris, labels = scene_meshes(x, cfg, occluder, obstacles)
    dirs_cam = camera.ray_directions()
    r = camera.world_from_camera[:3, :3]
    dirs = dirs_cam @ r.T
    t, prim, normals = _raycast(verts, tris, np.broadcast_to(camera.position, dirs.shape), dirs)
    hit = np.isfinite(t) & (prim != o3d.t.geometry.RaycastingScene.INVALID_ID)
    lab = np.where(hit, labels[np.where(hit, prim, 0)], -1)
    depth = np.where(hit, t, np.inf)
    # sensor noise grows with distance
    noisy = depth + rng.normal(0.0, 1.0, depth.shape) * (
        cfg.noise_base + cfg.noise_quad * np.where(hit, depth, 0) ** 2
    )
    valid = hit.copy()
    # depth edges: the far pixel of a jump is lost, the near one sometimes
    far_side = np.zeros_like(valid)
    near_side = np.zeros_like(valid)
    nearest = depth.copy()  # the nearest of each pixel and its four neighbours
    for axis in (0, 1):
        for shift in (1, -1):
            nb = np.roll(depth, shift, axis=axis)
            far_side |= nb < depth - cfg.edge_jump
            near_side |= nb > depth + cfg.edge_jump
            nearest = np.minimum(nearest, nb)
    valid &= ~far_side
    if cfg.flying_pixels > 0:
        noisy, flying = _flying_pixels(nearest, noisy, far_side & hit, cfg.flying_pixels, rng)
        valid |= flying
    valid &= ~(near_side & (rng.random(depth.shape) < cfg.edge_fg_drop))
    valid &= rng.random(depth.shape) >= cfg.dropout
    xyz = np.where(valid[..., None], dirs_cam * noisy[..., None], np.nan).astype(np.float32)
    # colour: base colour per label, Lambertian-ish shading, noise
    base = np.array([cfg.rope_rgb, cfg.table_rgb, cfg.gripper_rgb, cfg.occluder_rgb], dtype=np.float64)
    unit = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    shade = 0.35 + 0.65 * np.abs(np.sum(normals * unit, axis=-1))
    rgb = base[np.maximum(lab, 0)] * shade[..., None] + rng.normal(0.0, cfg.color_noise, dirs.shape)
    if cfg.color_shift_px:
        rgb = _shifted(np.where(hit[..., None], rgb, NOTHING_RGB), int(cfg.color_shift_px))
    rgb = np.where(valid[..., None], np.clip(rgb, 0, 255), 0).astype(np.uint8)
    visible = vertex_visibility(x, camera, verts, tris, labels, cfg.rope_radius)
    return xyz, rgb, visible


def _flying_pixels(near, noisy, far_side, share, rng):
    """Mixed pixels: a ``share`` of the ``far_side`` pixels of depth edges keep a depth drawn
    uniformly between their own surface and ``near``, the nearest neighbouring one (a
    time-of-flight or stereo sensor averages the two). Returns ``(noisy depth, which pixels fly)``."""
    flying = far_side & (rng.random(near.shape) < share)
    mix = rng.random(near.shape)
    out = noisy.copy()
    out[flying] = near[flying] + mix[flying] * (noisy[flying] - near[flying])
    return out, flying


def _shifted(rgb: np.ndarray, px: int) -> np.ndarray:
    """The colour image moved ``px`` pixels along its rows (positive: to larger u), the uncovered
    columns repeating the edge: a colour camera registered to the depth that far off."""
    out = np.roll(rgb, px, axis=1)
    if px > 0:
        out[:, :px] = rgb[:, :1]
    elif px < 0:
        out[:, px:] = rgb[:, -1:]
    return out
