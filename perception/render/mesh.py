"""Triangle meshes of the rendered scene: a tube along a smooth curve through the rod vertices, and boxes.

The rope is drawn through a centripetal Catmull-Rom spline (no overshoot at the short gripped edges)
so that the rendered rope bends smoothly between markers like a real one.
"""

from __future__ import annotations

import numpy as np


def catmull_rom(points: np.ndarray, samples_per_segment: int = 8, alpha: float = 0.5) -> np.ndarray:
    """(M, 3) points of a centripetal Catmull-Rom curve through ``points`` (n, 3), both ends included.

    Args:
        points: (n, 3) control points.
        samples_per_segment: points per segment.
        alpha: 0.5 is centripetal (no cusps or self-intersections within a segment).

    Returns:
        (M, 3).
    """
    p = np.asarray(points, dtype=np.float64)
    ext = np.concatenate([2 * p[:1] - p[1:2], p, 2 * p[-1:] - p[-2:-1]])
    p0, p1, p2, p3 = ext[:-3], ext[1:-2], ext[2:-1], ext[3:]

    def knot(a, b):
        return np.maximum(np.linalg.norm(b - a, axis=-1), 1e-9) ** alpha

    t0 = np.zeros(len(p1))
    t1 = t0 + knot(p0, p1)
    t2 = t1 + knot(p1, p2)
    t3 = t2 + knot(p2, p3)
    s = np.linspace(0.0, 1.0, samples_per_segment, endpoint=False)
    t = t1[:, None] + s[None, :] * (t2 - t1)[:, None]  # (S, k)

    def lerp(a, b, ta, tb):
        w = ((tb[:, None] - t) / (tb - ta)[:, None])[..., None]
        a = a[:, None] if a.ndim == 2 else a
        b = b[:, None] if b.ndim == 2 else b
        return w * a + (1 - w) * b

    a1, a2, a3 = lerp(p0, p1, t0, t1), lerp(p1, p2, t1, t2), lerp(p2, p3, t2, t3)
    b1, b2 = lerp(a1, a2, t0, t2), lerp(a2, a3, t1, t3)
    c = lerp(b1, b2, t1, t2)
    return np.concatenate([c.reshape(-1, 3), p[-1:]])


def tube(centre: np.ndarray, radius: float, sides: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an open tube around a polyline (frames parallel-transported along it).

    Args:
        centre: (M, 3) polyline.
        radius: tube radius [m].
        sides: vertices around each ring.

    Returns:
        ``(vertices (M sides, 3), triangles (T, 3) int)``.
    """
    c = np.asarray(centre, dtype=np.float64)
    tang = np.gradient(c, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    ref = np.array([0.0, 0.0, 1.0]) if abs(tang[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    normals = np.empty_like(c)
    nrm = np.cross(tang[0], ref)
    for i in range(len(c)):
        nrm = nrm - tang[i] * (nrm @ tang[i])
        norm = np.linalg.norm(nrm)
        nrm = np.cross(tang[i], ref) if norm < 1e-9 else nrm / norm
        normals[i] = nrm
    binormals = np.cross(tang, normals)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(ang)[None, :, None] * normals[:, None] + np.sin(ang)[None, :, None] * binormals[:, None]
    verts = (c[:, None] + radius * ring).reshape(-1, 3)
    i, k = np.meshgrid(np.arange(len(c) - 1), np.arange(sides), indexing="ij")
    a = i * sides + k
    b = i * sides + (k + 1) % sides
    tris = np.concatenate([np.stack([a, b, a + sides], -1), np.stack([b, b + sides, a + sides], -1)]).reshape(
        -1, 3
    )
    return verts, tris


_BOX_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
_BOX_TRIS = np.array(
    [
        [0, 1, 3],
        [0, 3, 2],
        [4, 6, 7],
        [4, 7, 5],
        [0, 4, 5],
        [0, 5, 1],
        [2, 3, 7],
        [2, 7, 6],
        [0, 2, 6],
        [0, 6, 4],
        [1, 5, 7],
        [1, 7, 3],
    ]
)


def box(centre: np.ndarray, axes: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An oriented box: ``axes`` (3, 3) columns are its unit axes, ``half`` its half extents.

    Args:
        centre: (3,) centre [m].
        axes: (3, 3) unit axes as columns.
        half: (3,) half extents [m].

    Returns:
        ``(vertices (8, 3), triangles (12, 3))``.
    """
    verts = np.asarray(centre) + (_BOX_CORNERS * np.asarray(half)) @ np.asarray(axes).T
    return verts, _BOX_TRIS.copy()


def frame_from_axis(axis: np.ndarray) -> np.ndarray:
    """(3, 3) orthonormal columns, the first along ``axis``.

    Args:
        axis: (3,) direction.

    Returns:
        (3, 3).
    """
    a = np.asarray(axis, dtype=np.float64)
    a = a / max(np.linalg.norm(a), 1e-12)
    ref = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    b = np.cross(a, ref)
    b /= np.linalg.norm(b)
    return np.stack([a, b, np.cross(a, b)], axis=1)


def plane(z: float, half: float = 3.0, centre=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A horizontal square at height ``z``.

    Args:
        z: height [m].
        half: half side [m].
        centre: (x, y) of its centre [m].

    Returns:
        ``(vertices (4, 3), triangles (2, 3))``.
    """
    cx, cy = centre
    verts = np.array(
        [
            [cx - half, cy - half, z],
            [cx + half, cy - half, z],
            [cx + half, cy + half, z],
            [cx - half, cy + half, z],
        ]
    )
    return verts, np.array([[0, 1, 2], [0, 2, 3]])


def cylinder(
    centre_xy, radius: float, z0: float, z1: float, sides: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """A closed vertical cylinder (a post) around the axis at ``centre_xy`` from height ``z0`` to ``z1``.

    Args:
        centre_xy: (2,) the axis [m].
        radius: radius [m].
        z0: bottom height [m].
        z1: top height [m].
        sides: vertices around each ring.

    Returns:
        ``(vertices (2 sides + 2, 3), triangles (4 sides, 3))``.
    """
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.stack([centre_xy[0] + radius * np.cos(ang), centre_xy[1] + radius * np.sin(ang)], -1)
    bottom = np.concatenate([ring, np.full((sides, 1), z0)], 1)
    top = np.concatenate([ring, np.full((sides, 1), z1)], 1)
    caps = np.array([[centre_xy[0], centre_xy[1], z0], [centre_xy[0], centre_xy[1], z1]])
    verts = np.concatenate([bottom, top, caps])
    k = np.arange(sides)
    k1 = (k + 1) % sides
    tris = np.concatenate(
        [
            np.stack([k, k1, k + sides], -1),
            np.stack([k1, k1 + sides, k + sides], -1),
            np.stack([np.full(sides, 2 * sides), k1, k], -1),
            np.stack([np.full(sides, 2 * sides + 1), k + sides, k1 + sides], -1),
        ]
    )
    return verts, tris
