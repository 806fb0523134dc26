"""DBSCAN on a few hundred points with a dense distance matrix and scipy's connected components.

Same result as sklearn's DBSCAN up to label order, without its per-call validation overhead
(several ms), which alone would break the tracker's latency budget.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components


def dbscan(points: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """(N,) cluster labels, -1 for noise. ``min_samples`` counts the point itself, as in sklearn.

    Args:
        points: (N, 3) points [m].
        eps: neighbourhood radius [m].
        min_samples: points (itself included) a core point needs within ``eps``.

    Returns:
        (N,) int labels.
    """
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    sq = (points * points).sum(1)
    d2 = sq[:, None] + sq[None] - 2.0 * points @ points.T
    near = d2 <= eps * eps
    core = near.sum(1) >= min_samples
    labels = np.full(n, -1, dtype=np.int64)
    if not core.any():
        return labels
    core_idx = np.flatnonzero(core)
    _, comp = connected_components(csr_matrix(near[np.ix_(core_idx, core_idx)]), directed=False)
    labels[core_idx] = comp
    border = np.flatnonzero(~core & near[:, core].any(1))
    if len(border):
        first_core = near[np.ix_(border, core_idx)].argmax(1)
        labels[border] = comp[first_core]
    return labels
