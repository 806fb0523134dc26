"""Small pieces the peer trackers share: cloud clean-up, kernels, LLE weights, node visibility.

Kept apart from the trackers so that each method's module holds only what its paper adds.
"""

from __future__ import annotations

import numpy as np

from deform import gripped_indices
from deform.io.arc_length import resample_vertices
from perception.camera import Camera
from perception.cloud import voxel_downsample, window_min


def clean_points(points: np.ndarray | None, voxel: float) -> np.ndarray:
    """(M, 3) finite points, voxel-downsampled (every method registers a thinned cloud).

    Args:
        points: (N, 3) points [m] or None.
        voxel: cell size [m]; 0 keeps every point.

    Returns:
        (M, 3) float64, M <= N (possibly 0).
    """
    if points is None:
        return np.zeros((0, 3))
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[-1] != 3:
        pts = pts.reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    return voxel_downsample(pts, voxel) if len(pts) else pts


def edge_lengths(x: np.ndarray) -> np.ndarray:
    """(n-1,) lengths of the edges of the polyline ``x`` (n, 3) [m]."""
    return np.linalg.norm(np.diff(x, axis=0), axis=1)


def pin(x: np.ndarray, grip: np.ndarray) -> np.ndarray:
    """A copy of ``x`` (n, 3) with nodes 0, 1, n-2, n-1 set to ``grip`` (4, 3)."""
    out = np.array(x, dtype=np.float64)
    out[gripped_indices(len(out))] = grip
    return out


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) squared Euclidean distances."""
    return np.maximum((a * a).sum(1)[:, None] - 2 * a @ b.T + (b * b).sum(1)[None], 0.0)


def gaussian_kernel(x: np.ndarray, beta: float) -> np.ndarray:
    """G_ij = exp(-|x_i - x_j|^2 / (2 beta^2)), the motion-coherence kernel of CPD."""
    return np.exp(-squared_distances(x, x) / (2 * beta * beta))


def lle_weights(x: np.ndarray, neighbours: np.ndarray, reg: float = 1e-3) -> np.ndarray:
    """(n, n) locally-linear-embedding weights: each node as the affine combination of its
    neighbours that best reproduces it (Roweis & Saul 2000), rows summing to 1.

    The local Gram matrix is regularised by ``reg`` times its trace: with more neighbours than
    dimensions (or collinear nodes) it is singular.

    Args:
        x: (n, 3) nodes [m].
        neighbours: (n, k) indices of each node's neighbours.
        reg: relative Tikhonov regularisation.

    Returns:
        (n, n) W.
    """
    n, k = neighbours.shape
    w = np.zeros((n, n))
    for i in range(n):
        z = x[neighbours[i]] - x[i]
        gram = z @ z.T
        gram += np.eye(k) * reg * max(np.trace(gram), 1e-12)
        wi = np.linalg.solve(gram, np.ones(k))
        w[i, neighbours[i]] = wi / wi.sum()
    return w


def knn_neighbours(x: np.ndarray, k: int) -> np.ndarray:
    """(n, k) each node's k nearest other nodes in space."""
    d = squared_distances(x, x)
    np.fill_diagonal(d, np.inf)
    return np.argsort(d, axis=1)[:, :k]


def lle_matrix(w: np.ndarray) -> np.ndarray:
    """H = (I - W)^T (I - W): ||(I - W) Y||^2 = tr(Y^T H Y) penalises departures from the LLE shape."""
    a = np.eye(len(w)) - w
    return a.T @ a


def depth_occluded(
    x: np.ndarray, depth: np.ndarray, camera: Camera, margin: float, window: int = 1
) -> np.ndarray:
    """(n,) True where the depth image shows something at least ``margin`` in front of the node, or
    the node is outside the image or behind the camera.

    Args:
        x: (n, 3) nodes, world frame [m].
        depth: (H, W) observed depth [m], NaN where unknown.
        camera: the camera.
        margin: how much closer the scene must be [m].
        window: half size of the pixel window searched [pixels].

    Returns:
        (n,) bool.
    """
    uv, z = camera.project(camera.to_camera(x))
    seen = window_min(np.asarray(depth, dtype=np.float64), uv, window)
    inside = (
        (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    )
    return (np.isfinite(seen) & (seen < z - margin)) | ~inside


def mask_image(points: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) bool: the pixels the world-frame rope ``points`` project to (the segmentation mask)."""
    mask = np.zeros((camera.height, camera.width), dtype=bool)
    if len(points) == 0:
        return mask
    uv, z = camera.project(camera.to_camera(points))
    ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
    u, v = np.floor(uv[ok, 0]).astype(np.int64), np.floor(uv[ok, 1]).astype(np.int64)
    keep = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    mask[v[keep], u[keep]] = True
    return mask


def arc_coordinates(x: np.ndarray) -> np.ndarray:
    """(n,) arc length [m] from node 0 to each node of the polyline ``x`` (n, 3)."""
    return np.concatenate([[0.0], np.cumsum(edge_lengths(x))])


def node_count(x0: np.ndarray, count: int | None, spacing: float | None) -> int:
    """How many nodes a peer puts on the rope ``x0`` (n, 3): ``count`` if given, else one every
    ``spacing`` [m] between the gripped nodes 1 and n-2 (plus the 2 outer gripped nodes), else n."""
    if count is not None:
        return max(int(count), 5)
    if spacing is not None and spacing > 0:
        inner = float(arc_coordinates(x0[1:-1])[-1])
        return max(round(inner / spacing), 2) + 3
    return len(x0)


def resample_nodes(x0: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``x0`` (m, 3) resampled to ``n`` nodes along its polyline, keeping the gripped nodes: nodes 0,
    1, n-2, n-1 are x0[0], x0[1], x0[-2], x0[-1]; nodes 1..n-2 are evenly spaced in arc length
    between x0[1] and x0[-2].

    Args:
        x0: (m, 3) nodes [m], m >= 4.
        n: nodes wanted, n >= 4.

    Returns:
        ``(nodes, arc)``: (n, 3) nodes and (n,) their arc-length coordinates along ``x0`` [m] (the
        length of rope between two nodes, which their chord can only underestimate).
    """
    x0 = np.asarray(x0, dtype=np.float64)
    s = arc_coordinates(x0)
    t = np.concatenate([[s[0]], np.linspace(s[1], s[-2], n - 2), [s[-1]]])
    return resample_vertices(x0, n), t
