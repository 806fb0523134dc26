r"""The rope's length as the camera sees it, against the model's rest length.

A model of another rope (or one whose length was given wrong) keeps its own rest lengths: every
correction is projected back onto them, so a rope that is in truth 2 % shorter is pushed into a
sag or a bulge the camera never shows, however well each cloud is explained before the projection.
The camera measures the free rope's length whenever it sees it whole:

- the rope points are ordered along the corrected estimate (the arc length :math:`s` of each
  point's nearest point on the polyline through vertices 1..n-2) and averaged in ``bins_per_edge``
  bins per edge;
- the length is that of the polyline from vertex 1 through the bin means to vertex n-2.

Bin means of an arc lie inside it, which shortens the polyline by a relative :math:`(\kappa b)^2/24`
for curvature :math:`\kappa` and bin length :math:`b` (0.3 % for a 20 cm bend radius and 5 cm bins);
a GMM with one component per vertex (:mod:`perception.estimate`) has bins twice as long and its
means are pulled further in, which is why its corrected shape is not the measure. A cloud with an
empty bin (occlusion, the rope leaving the image) gives no measurement: a gap bridged straight is
shorter than the rope.
"""

from __future__ import annotations

import numpy as np

from perception.polyline import arc_positions


def seen_length(
    points: np.ndarray, x: np.ndarray, radius: float, bins_per_edge: int = 2, min_points: int = 2
) -> float | None:
    """Length of the free rope (vertex 1 to n-2) that the rope ``points`` show, or None when part of
    it is not shown.

    Args:
        points: (N, 3) segmented rope points, world frame [m] (downsampled is fine).
        x: (n, 3) the corrected estimate, n >= 4 [m].
        radius: points farther than this from the estimate are not the rope [m].
        bins_per_edge: bins per free edge.
        min_points: points a bin needs.

    Returns:
        The length [m], or None.
    """
    free = np.asarray(x, dtype=np.float64)[1:-1]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(free) < 2 or len(pts) == 0:
        return None
    s, d = arc_positions(pts, free)
    total = float(np.linalg.norm(np.diff(free, axis=0), axis=1).sum())
    near = d < radius
    n_bins = bins_per_edge * (len(free) - 1)
    b = np.minimum((s[near] / max(total, 1e-9) * n_bins).astype(int), n_bins - 1)
    counts = np.bincount(b, minlength=n_bins)
    if counts.min() < min_points:
        return None
    means = np.stack([np.bincount(b, weights=pts[near][:, k], minlength=n_bins) for k in range(3)], 1)
    means /= counts[:, None]
    path = np.vstack([free[:1], means, free[-1:]])
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
