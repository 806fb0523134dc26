"""Every peer tracker behind the one interface: its own published node density (resampled from the
given nodes, gripped nodes kept), it follows a moving rendered-like rope closely without its nodes
sliding along it, keeps its estimate on an empty cloud, and the factory knows exactly the names."""

import numpy as np
import pytest

from perception.baselines import PEERS, PeerTracker, make_peer
from perception.baselines.common import arc_coordinates
from tests.perception.baselines.conftest import GRIP, at_fractions, moving_rope, rope, tube, two_way_error

PUBLISHED = {"cpd": 29, "cdcpd": 29, "trackdlo": 45, "upetrack": 45}  # on this 0.92 m rope


@pytest.mark.parametrize("name", PEERS)
def test_resamples_to_its_own_density_keeping_the_gripped_nodes(name):
    _, x0 = rope()
    peer = make_peer(name)
    y = peer.initialize(x0, x0[GRIP])
    assert len(y) == PUBLISHED[name]
    np.testing.assert_allclose(y[[0, 1, -2, -1]], x0[GRIP])
    np.testing.assert_allclose(peer.s0[1:-1], np.linspace(peer.s0[1], peer.s0[-2], len(y) - 2))
    assert arc_coordinates(y)[-1] == pytest.approx(arc_coordinates(x0)[-1], rel=2e-3)  # on the polyline
    assert len(make_peer(name, nodes=20).initialize(x0, x0[GRIP])) == 20


def track(name, frames, seed=0):
    rng = np.random.default_rng(seed)
    _, x0 = rope()
    peer = make_peer(name)
    peer.initialize(x0, x0[GRIP])
    frac = peer.s0 / peer.s0[-1]
    errors, slide = [], []
    for curve, x in frames:
        y = peer.update(tube(curve, rng), x[GRIP])
        errors.append(two_way_error(y, curve))
        slide.append(np.linalg.norm(y - at_fractions(curve, frac), axis=1))
    return np.array(errors), np.array(slide)


# the largest two-way error over 24 frames (measured 2.0, 7.6, 2.2, 2.0 mm: CDCPD's 2 cm voxels and
# its edges held to their length of rope cost it a few mm on a tube's surface points)
ERROR = {"cpd": 0.004, "cdcpd": 0.009, "trackdlo": 0.004, "upetrack": 0.004}
# the worst node's distance from its own place on the rope after 24 frames (measured 14, 19, 15, 47
# mm): nodes that slide along the rope fail this though their two-way error stays small. UPETrack's
# free mixture has nothing against sliding; the others' coherence does.
SLIDE = {"cpd": 0.025, "cdcpd": 0.03, "trackdlo": 0.025, "upetrack": 0.07}


@pytest.mark.parametrize("name", PEERS)
def test_follows_a_moving_rope_closely_without_sliding(name):
    """24 frames, 3.7-7.5 mm a frame and turning: the error stays within a few mm throughout (the
    points are on the tube's surface, 5 mm off the centreline). Before the fixes TrackDLO and
    UPETrack drifted to 21-24 mm on such a case."""
    errors, slide = track(name, moving_rope())
    assert errors.max() < ERROR[name], errors
    assert slide[-1].max() < SLIDE[name], slide[-1]


@pytest.mark.parametrize("name", PEERS)
def test_empty_cloud_keeps_the_estimate_and_moves_the_grippers(name):
    _, x0 = rope()
    peer = make_peer(name)
    y0 = peer.initialize(x0, x0[GRIP])
    held = [0, 1, len(y0) - 2, len(y0) - 1]
    free = np.setdiff1d(np.arange(len(y0)), held)
    grip = x0[GRIP] + [0.01, 0.0, 0.0]
    for empty in (np.zeros((0, 3)), np.full((5, 3), np.nan), None):
        y = peer.update(empty, grip)
        np.testing.assert_allclose(y[free], y0[free])
        np.testing.assert_allclose(y[held], grip)


@pytest.mark.parametrize("name", PEERS)
def test_is_a_peer_tracker(name):
    assert isinstance(make_peer(name), PeerTracker)
    assert make_peer(name).name == name


def test_unknown_name_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="cpd, cdcpd, trackdlo, upetrack"):
        make_peer("spr")
