"""Finding the rope again from the segmented cloud alone, and noticing when that is needed.

A correction (:mod:`perception.estimate`) only uses points within ``filter_radius`` of the
prediction, so it cannot repair an estimate that has drifted further (the rope was hidden for a
while, moved faster than the model followed, or the model is of another rope). Two pieces:

- :func:`disagreement`: the share of the visible rope points that the estimate does not explain
  (farther than a radius from its polyline). Occlusion hides points but never makes one
  unexplained, so this stays low under occlusion and rises only when the estimate is elsewhere.
- :func:`rope_from_points`: a model-free estimate. The points (voxel-downsampled) and the two
  inner gripped vertices become nodes of a Euclidean minimum spanning tree; the tree path from one
  gripper to the other orders the rope (side branches: rope thickness, clutter, stray points, are
  left off the path; gaps left by occlusion are bridged by the shortest jump, which is what a
  spanning tree does). Points near the path are given the arc length of their nearest path node,
  averaged in bins along the path, and the rod's vertices are placed on that backbone at its rest
  lengths (scaled to the backbone's length: a gap bridged straight is shorter than the rope).

Written by hand: the ordering needs the gripper anchors and the rest lengths of this rod, which no
point-cloud library's curve fitting takes; the graph work itself is scipy's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial.distance import cdist

from perception.cloud import voxel_downsample
from perception.initial import place_by_arclength
from perception.polyline import segment_distances

MAX_NODES = 600  # the spanning tree is built on a dense distance matrix: (MAX_NODES + 2)^2 floats


def disagreement(points: np.ndarray, x: np.ndarray, radius: float) -> float:
    """Share of ``points`` farther than ``radius`` from the polyline through ``x``.

    Args:
        points: (N, 3) rope points, world frame [m], N > 0.
        x: (n, 3) the estimate's vertices [m].
        radius: what a correction can still explain [m].

    Returns:
        A fraction in [0, 1].
    """
    return float(np.mean(segment_distances(points, x) > radius))


def explained_cost(points: np.ndarray, x: np.ndarray, cap: float) -> float:
    """Mean distance of ``points`` to the polyline through ``x``, each capped at ``cap`` [m]: how
    well a shape explains a cloud, robust to stray points."""
    return float(np.minimum(segment_distances(points, x), cap).mean())


def tree_path(nodes: np.ndarray, source: int, target: int) -> np.ndarray:
    """Indices of the path from ``source`` to ``target`` in the Euclidean minimum spanning tree of
    ``nodes`` (M, 3)."""
    dist = cdist(nodes, nodes)
    dist[dist == 0] = 1e-12  # coincident points stay connected (a zero is "no edge" to scipy)
    np.fill_diagonal(dist, 0.0)
    tree = minimum_spanning_tree(dist)
    _, parent = breadth_first_order(tree, source, directed=False, return_predecessors=True)
    path = [target]
    while path[-1] != source and parent[path[-1]] >= 0:
        path.append(int(parent[path[-1]]))
    return np.array(path[::-1])


def backbone(points: np.ndarray, start: np.ndarray, end: np.ndarray, bin_size: float) -> np.ndarray:
    """(K, 3) a smooth polyline from ``start`` to ``end`` through the rope ``points``.

    Args:
        points: (N, 3) rope points, already downsampled [m].
        start: (3,) where the rope leaves the first gripper (vertex 1) [m].
        end: (3,) where it enters the second (vertex n-2) [m].
        bin_size: arc length over which points are averaged [m] (a few rope diameters).

    Returns:
        (K, 3), ``start`` first and ``end`` last.
    """
    nodes = np.vstack([start, points, end])
    path = tree_path(nodes, 0, len(nodes) - 1)
    along = nodes[path]
    s_path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(along, axis=0), axis=1))])
    d = cdist(points, along)
    near = d.min(1) < bin_size  # points of side branches (clutter, stray returns) stay out
    s = s_path[d.argmin(1)][near]
    bins = np.floor(s / max(bin_size, 1e-6)).astype(int)
    means = [points[near][bins == b].mean(0) for b in np.unique(bins)]
    return np.vstack([start, *means, end])


def rope_from_points(
    points: np.ndarray, grip: np.ndarray, rest: np.ndarray, voxel: float = 0.01, bin_size: float = 0.03
) -> np.ndarray | None:
    """(n, 3) the rod placed along the rope seen in ``points``, or None when there are too few.

    Args:
        points: (N, 3) segmented rope points, world frame [m].
        grip: (4, 3) vertices 0, 1, n-2, n-1 held by the grippers [m].
        rest: (n-1,) edge rest lengths [m].
        voxel: downsampling cell [m] (also what keeps the tree small).
        bin_size: arc length over which points are averaged into the backbone [m].

    Returns:
        (n, 3) vertices with the gripped ones at ``grip``, or None.
    """
    grip = np.asarray(grip, dtype=np.float64).reshape(4, 3)
    pts = voxel_downsample(np.asarray(points, dtype=np.float64).reshape(-1, 3), voxel)
    if len(pts) < 5:
        return None
    if len(pts) > MAX_NODES:
        pts = pts[np.random.default_rng(0).choice(len(pts), MAX_NODES, replace=False)]
    curve = backbone(pts, grip[1], grip[2], bin_size)
    n = len(rest) + 1
    x = np.empty((n, 3))
    x[[0, 1, n - 2, n - 1]] = grip
    x[1 : n - 1] = place_by_arclength(curve, np.asarray(rest)[1 : n - 2])
    x[1], x[n - 2] = grip[1], grip[2]
    return x


@dataclass
class TrackingHealth:
    """Whether the estimate follows the rope, and how often it lost and found it again.

    ``state``: ``"tracking"`` (the camera agrees with the estimate, or no cloud has come yet),
    ``"lost"`` (the visible rope is mostly outside what a correction can reach, or the rope has not
    been seen for ``lost_after_s``). ``lost`` and ``recovered`` count the transitions;
    ``since_seen_steps`` counts model steps since a cloud last showed the rope;
    ``disagreement`` is the last cloud's share of unexplained rope points; ``length_scale`` the free
    rope's rest length over the model's own, after the camera's length replaced it
    (:mod:`perception.length`; 1 while the two agree); ``camera_over_model_mm`` how far across the
    rope the last cloud put its observed vertices from where the model's rest lengths let the state
    lie (mean, mm: the camera's depth noise alone, or a model that cannot take the shape seen);
    ``depth_noise_mm`` the depth noise the last cloud showed at the rope's depths, which sets the
    occlusion margin when it is the larger (:func:`perception.cloud.depth_noise`)."""

    state: str = "tracking"
    lost: int = 0
    recovered: int = 0
    redetected: int = 0
    since_seen_steps: float = float("inf")
    disagreement: float | None = None
    length_scale: float = 1.0
    camera_over_model_mm: float | None = None
    depth_noise_mm: float | None = None

    def lose(self) -> None:
        if self.state != "lost":
            self.state = "lost"
            self.lost += 1

    def recover(self, redetected: bool) -> None:
        if self.state == "lost":
            self.state = "tracking"
            self.recovered += 1
        self.redetected += int(redetected)

    def as_dict(self, dt: float) -> dict:
        """Plain values for a status reply (``since_seen_s``: None before the rope was ever seen)."""
        since = self.since_seen_steps * dt
        return {
            "state": self.state,
            "lost": self.lost,
            "recovered": self.recovered,
            "redetected": self.redetected,
            "since_seen_s": None if not np.isfinite(since) else round(float(since), 4),
            "disagreement": None if self.disagreement is None else round(self.disagreement, 4),
            "length_scale": round(float(self.length_scale), 4),
            "camera_over_model_mm": None
            if self.camera_over_model_mm is None
            else round(float(self.camera_over_model_mm), 3),
            "depth_noise_mm": None if self.depth_noise_mm is None else round(float(self.depth_noise_mm), 2),
        }
