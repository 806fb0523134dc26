"""Peer trackers: the published deformable-linear-object trackers, re-implemented from their papers
as baselines for the DEFORM tracker, all behind one interface (:class:`PeerTracker`).

    from perception.baselines import PEERS, make_peer
    peer = make_peer("trackdlo")                       # or "cpd", "cdcpd", "upetrack"; keyword overrides
    x = peer.initialize(x0, grip)                      # x0 (n, 3) true first-frame nodes, grip (4, 3)
    x = peer.update(points_world, grip, depth, camera) # every camera frame; never raises on a bad cloud

- ``cpd``: Coherent Point Drift, frame to frame (Myronenko & Song 2010); the EM core of the others.
- ``cdcpd``: CPD + LLE + a QP onto edge-length and gripper constraints (Chi et al. 2019).
- ``trackdlo``: geodesic-kernel CPD with visibility priors and motion coherence (Xiang et al. 2023).
- ``upetrack``: a GMM on the visible nodes and closed-form placement of the occluded ones
  (Wu et al. 2025); only partly published, see its module for what was assumed.

Each module's docstring gives the paper, the update's maths and its departures from the paper.
"""

from __future__ import annotations

from perception.baselines.interface import BaselineTracker, PeerTracker

PEERS = ("cpd", "cdcpd", "trackdlo", "upetrack")


def make_peer(name: str, **kw) -> PeerTracker:
    """A fresh peer tracker by name, its parameters overridden by ``kw``.

    Args:
        name: one of :data:`PEERS`.
        **kw: constructor arguments of that tracker (e.g. ``voxel=0.01``).

    Returns:
        The tracker (not yet initialised).

    Raises:
        ValueError: unknown name.
    """
    key = str(name).strip().lower()
    if key == "cpd":
        from perception.baselines.cpd import CPDTracker as cls
    elif key == "cdcpd":
        from perception.baselines.cdcpd import CDCPDTracker as cls
    elif key == "trackdlo":
        from perception.baselines.trackdlo import TrackDLOTracker as cls
    elif key == "upetrack":
        from perception.baselines.upetrack import UPETrackTracker as cls
    else:
        raise ValueError(f"unknown peer tracker {name!r}; choose one of {', '.join(PEERS)}")
    return cls(**kw)


__all__ = ["PEERS", "BaselineTracker", "PeerTracker", "make_peer"]
