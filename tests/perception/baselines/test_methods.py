"""What each method's paper adds: CDCPD's constraints, TrackDLO's motion coherence through an
occlusion, UPETrack's placement of occluded nodes."""

import numpy as np

from perception.baselines import make_peer
from perception.baselines.cdcpd import project_constraints
from tests.perception.baselines.conftest import GRIP, rope


def test_cdcpd_output_respects_edge_lengths_and_grippers():
    rng = np.random.default_rng(1)
    _, x0 = rope()
    peer = make_peer("cdcpd", stretch=0.05)
    peer.initialize(x0, x0[GRIP])
    pts, x = rope(shift=(0.0, 0.0, 0.01))
    pts = pts * [1.2, 1.0, 1.0]  # a stretched cloud: the registration alone would over-stretch
    grip = x[GRIP] + [0.002, 0.0, 0.0]
    y = peer.update(pts + rng.normal(0, 0.002, pts.shape), grip)
    edges = np.linalg.norm(np.diff(y, axis=0), axis=1)
    assert np.all(edges <= 1.05 * peer.rest * 1.002)
    np.testing.assert_allclose(y[GRIP], grip, atol=1e-9)


def test_cdcpd_projection_shortens_only_what_is_too_long():
    y = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.3, 0, 0], [0.4, 0, 0]])
    out = project_constraints(y, y, np.full(3, 0.12), np.array([0]), y[:1])
    assert np.all(np.linalg.norm(np.diff(out, axis=0), axis=1) <= 0.12 + 1e-5)
    np.testing.assert_allclose(out[0], y[0], atol=1e-9)


def occluded_frames(hidden):
    """The rope moving sideways 4 mm a frame with the points of nodes ``hidden`` removed."""
    frames = []
    for f in range(1, 6):
        pts, x = rope(shift=(0.0, 0.004 * f, 0.0))
        s = np.linspace(0, 1, len(pts))
        lo, hi = (hidden[0] - 0.5) / 12, (hidden[-1] + 0.5) / 12
        frames.append((pts[(s < lo) | (s > hi)], x))
    return frames


def test_trackdlo_carries_a_hidden_segment_with_the_visible_rope():
    _, x0 = rope()
    peer = make_peer("trackdlo")
    peer.initialize(x0, x0[GRIP])
    for pts, x in occluded_frames([5, 6, 7]):
        y = peer.update(pts, x[GRIP])
    assert not peer.visible[6]
    moved = y[5:8, 1] - x0[5:8, 1]
    assert np.all(moved > 0.01)  # the true move is 2 cm; a frozen node would show 0
    assert np.linalg.norm(y[5:8] - x[5:8], axis=1).max() < 0.01


def test_upetrack_places_hidden_nodes_near_the_rope():
    _, x0 = rope()
    peer = make_peer("upetrack")
    peer.initialize(x0, x0[GRIP])
    for pts, x in occluded_frames([5, 6]):
        y = peer.update(pts, x[GRIP])
    assert not peer.visible[5] and not peer.visible[6]
    assert np.all(y[5:7, 1] - x0[5:7, 1] > 0.01)  # carried sideways with the rope (2 cm)
    # the straight-continuation term overshoots at the bottom of the sag: a loose bound
    assert np.linalg.norm(y[5:7] - x[5:7], axis=1).max() < 0.03
    # each one-directional estimate keeps the rest length; their blend nearly does
    np.testing.assert_allclose(np.linalg.norm(y[6] - y[5]), peer.rest[5], rtol=0.1)
