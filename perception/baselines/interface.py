"""The one interface every peer tracker (baseline) offers, and the plumbing they share.

A benchmark drives each peer the same way: :meth:`PeerTracker.initialize` with the true first-frame
nodes (each peer resamples them to its own published node density), then :meth:`PeerTracker.update`
once per camera frame with the segmented rope points in the world frame and the gripped nodes.
:class:`BaselineTracker` holds what is common: the state, the resampling, the gripped-node
bookkeeping, the clean-up of the cloud and the rule that an update never raises (a bad or empty
cloud keeps the last estimate; the gripped nodes always follow ``grip``).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from perception.baselines.common import clean_points, edge_lengths, node_count, pin, resample_nodes

if TYPE_CHECKING:
    from perception.camera import Camera

log = logging.getLogger(__name__)

# fewer points than this and no registration is attempted (a mixture needs some evidence)
MIN_POINTS = 3


@runtime_checkable
class PeerTracker(Protocol):
    """A published deformable-linear-object tracker behind the benchmark's interface."""

    name: str

    def initialize(self, x0: np.ndarray, grip: np.ndarray) -> np.ndarray:
        """(k, 3) estimate from the initial nodes ``x0`` (n, 3) [m] and ``grip`` (4, 3): nodes
        0, 1, n-2, n-1 held by the grippers, world frame. The peer tracks its own k nodes (its
        published density): x0 resampled along its polyline, keeping the four gripped nodes."""
        ...

    def update(
        self,
        points: np.ndarray,
        grip: np.ndarray,
        depth: np.ndarray | None = None,
        camera: Camera | None = None,
    ) -> np.ndarray:
        """(k, 3) estimate after one camera frame: ``points`` (N, 3) segmented rope points, world
        frame (may be empty); ``grip`` (4, 3); ``depth`` (H, W) observed depth [m], NaN = none, and
        its ``camera`` for visibility reasoning. Never raises on an empty or degenerate cloud."""
        ...


class BaselineTracker:
    """State and safety shared by the peers; a subclass supplies :meth:`_setup` and :meth:`_register`.

    ``voxel``: the cell size [m] the cloud is downsampled to before registration (each method's own
    published value where there is one). ``node_count`` or ``node_spacing`` [m]: the method's
    published node density; :meth:`initialize` resamples the given nodes to it (``nodes`` overrides
    it with a count). The grippers hold nodes 0, 1, k-2, k-1 of the peer's own k nodes.
    """

    name = "baseline"
    voxel = 0.008
    node_count: int | None = None
    node_spacing: float | None = None

    def __init__(self, nodes: int | None = None) -> None:
        self.nodes = nodes
        self.x: np.ndarray | None = None
        self.x0: np.ndarray | None = None
        self.rest: np.ndarray | None = None
        self.grip: np.ndarray | None = None

    def initialize(self, x0: np.ndarray, grip: np.ndarray) -> np.ndarray:
        x0 = np.asarray(x0, dtype=np.float64).reshape(-1, 3)
        if len(x0) < 5 or not np.all(np.isfinite(x0)):
            raise ValueError(f"need at least 5 finite nodes, got shape {x0.shape}")
        grip = np.asarray(grip, dtype=np.float64).reshape(4, 3)
        count = self.nodes if self.nodes is not None else self.node_count
        x0, self.s0 = resample_nodes(x0, node_count(x0, count, self.node_spacing))
        self.x0 = x0
        self.rest = edge_lengths(x0)
        self.grip = grip.copy()
        self.x = pin(x0, grip)
        self._setup(self.x0)
        return self.x.copy()

    def update(
        self,
        points: np.ndarray,
        grip: np.ndarray,
        depth: np.ndarray | None = None,
        camera: Camera | None = None,
    ) -> np.ndarray:
        if self.x is None:
            raise RuntimeError(f"{self.name}: update() before initialize()")
        g = np.asarray(grip, dtype=np.float64)
        if g.shape == (4, 3) and np.all(np.isfinite(g)):
            self.grip = g.copy()
        try:
            pts = clean_points(points, self.voxel)
            if len(pts) >= MIN_POINTS:
                x = self._register(pts, self.grip, depth, camera)
                if np.all(np.isfinite(x)):
                    self.x = np.asarray(x, dtype=np.float64)
                else:
                    log.warning("%s: non-finite registration; keeping the last estimate", self.name)
        except Exception as exc:  # a peer must not stop the benchmark's loop
            log.warning("%s: update failed (%s); keeping the last estimate", self.name, exc)
        self.x = pin(self.x, self.grip)
        return self.x.copy()

    # ----- for subclasses --------------------------------------------------------------------
    def _setup(self, x0: np.ndarray) -> None:
        """Precompute what depends only on the initial shape (kernels, LLE weights)."""

    def _register(
        self, points: np.ndarray, grip: np.ndarray, depth: np.ndarray | None, camera: Camera | None
    ) -> np.ndarray:
        raise NotImplementedError
