"""Every peer tracker behind the one interface: it follows a moving synthetic rope, keeps its
estimate on an empty cloud, and the factory knows exactly the published names."""

import numpy as np
import pytest

from perception.baselines import PEERS, PeerTracker, make_peer
from tests.perception.baselines.conftest import GRIP, rope


def track(name, frames, seed=0):
    rng = np.random.default_rng(seed)
    _, x0 = rope()
    peer = make_peer(name)
    peer.initialize(x0, x0[GRIP])
    for pts, x in frames:
        y = peer.update(pts + rng.normal(0, 0.002, pts.shape), x[GRIP])
    return y, x


@pytest.mark.parametrize("name", PEERS)
def test_follows_a_translation_onto_the_rope(name):
    """1.5 cm in 5 frames: the nodes end on the moved rope and, on average, near their true places
    (registration lets nodes slide along the rope, so the per-node bound is looser)."""
    frames = [rope(shift=(0.003 * f, -0.002 * f, 0.001 * f)) for f in range(1, 6)]
    y, x = track(name, frames)
    curve = frames[-1][0]
    to_curve = np.sqrt(((y[:, None] - curve[None]) ** 2).sum(-1)).min(1)
    assert to_curve.mean() < 0.004, to_curve
    assert np.linalg.norm(y - x, axis=1).mean() < 0.02


@pytest.mark.parametrize("name", PEERS)
def test_empty_cloud_keeps_the_estimate_and_moves_the_grippers(name):
    _, x0 = rope()
    peer = make_peer(name)
    peer.initialize(x0, x0[GRIP])
    grip = x0[GRIP] + [0.01, 0.0, 0.0]
    for empty in (np.zeros((0, 3)), np.full((5, 3), np.nan), None):
        y = peer.update(empty, grip)
        free = np.setdiff1d(np.arange(13), GRIP)
        np.testing.assert_allclose(y[free], x0[free])
        np.testing.assert_allclose(y[GRIP], grip)


@pytest.mark.parametrize("name", PEERS)
def test_is_a_peer_tracker(name):
    assert isinstance(make_peer(name), PeerTracker)
    assert make_peer(name).name == name


def test_unknown_name_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="cpd, cdcpd, trackdlo, upetrack"):
        make_peer("spr")
