"""What each method's paper adds: CDCPD's constraints, TrackDLO's motion coherence through an
occlusion, UPETrack's placement of occluded nodes."""

import numpy as np

from perception.baselines import make_peer
from perception.baselines.cdcpd import project_constraints
from tests.perception.baselines.conftest import GRIP, at_fractions, rope, to_polyline


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
    # the gripped edges are the grippers'; every other edge at most 5 % over its length of rope
    assert np.all(edges[1:-1] <= 1.05 * np.diff(peer.s0)[1:-1] * 1.002)
    np.testing.assert_allclose(y[[0, 1, -2, -1]], grip, atol=1e-9)


def test_cdcpd_projection_shortens_only_what_is_too_long():
    y = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.3, 0, 0], [0.4, 0, 0]])
    out = project_constraints(y, y, np.full(3, 0.12), np.array([0]), y[:1])
    assert np.all(np.linalg.norm(np.diff(out, axis=0), axis=1) <= 0.12 + 1e-5)
    np.testing.assert_allclose(out[0], y[0], atol=1e-9)


LO, HI = 0.4, 0.6  # the arc-length fractions of the rope hidden


def occluded_frames():
    """The rope moving sideways 4 mm a frame with the points of its middle fifth removed."""
    frames = []
    for f in range(1, 6):
        pts, x = rope(shift=(0.0, 0.004 * f, 0.0))
        s = np.linspace(0, 1, len(pts))
        frames.append((pts[(s < LO) | (s > HI)], x, pts))
    return frames


def hidden_run(peer):
    """The peer's nodes well inside the hidden fifth."""
    frac = peer.s0 / peer.s0[-1]
    return np.flatnonzero((frac > LO + 0.03) & (frac < HI - 0.03))


def test_trackdlo_carries_a_hidden_segment_with_the_visible_rope():
    _, x0 = rope()
    peer = make_peer("trackdlo")
    y0 = peer.initialize(x0, x0[GRIP])
    frames = occluded_frames()
    for pts, x, _ in frames:
        y = peer.update(pts, x[GRIP])
    curve = frames[-1][2]
    run = hidden_run(peer)
    assert not peer.visible[run].any()
    assert np.all(y[run, 1] - y0[run, 1] > 0.01)  # the true move is 2 cm; a frozen node would show 0
    assert to_polyline(y[run], curve).max() < 0.01


def test_upetrack_places_hidden_nodes_near_the_rope():
    _, x0 = rope()
    peer = make_peer("upetrack")
    y0 = peer.initialize(x0, x0[GRIP])
    frames = occluded_frames()
    for pts, x, _ in frames:
        y = peer.update(pts, x[GRIP])
    curve = frames[-1][2]
    run = hidden_run(peer)
    assert not peer.visible[run].any()
    assert np.all(y[run, 1] - y0[run, 1] > 0.01)  # carried sideways with the rope (2 cm)
    # the straight-continuation term overshoots at the bottom of the sag: a loose bound
    assert to_polyline(y[run], curve).max() < 0.03
    # each one-directional estimate keeps the rest length; their blend nearly does
    np.testing.assert_allclose(np.linalg.norm(np.diff(y[run], axis=0), axis=1), peer.rest[run[:-1]], rtol=0.1)


def test_trackdlo_follows_a_rendered_recording(data_root):
    """60 camera frames (2 s) of DLO1 recording 100 rendered at 30 fps, fully visible: TrackDLO
    within a few mm (the floor is the rope's radius: the points are on its surface)."""
    from deform import gripped_indices, load_recording
    from perception import render_recording
    from perception.cloud import depth_image
    from perception.config import load_config
    from perception.segment import segment_rope

    rec = load_recording(data_root / "DLO1" / "eval" / "100.pkl").positions[:200]
    cfg = load_config()
    gi = gripped_indices(rec.shape[1])
    peer = make_peer("trackdlo")
    peer.initialize(rec[0], rec[0, gi])
    errors = []
    for f in render_recording(rec, dt=0.01, fps=30, seed=0)[:60]:
        pts = f.camera.to_world(segment_rope(f.xyz, f.rgb, cfg.segmentation))
        y = peer.update(pts, rec[f.step, gi], depth_image(f.xyz, f.camera), f.camera)
        dense = at_fractions(rec[f.step], np.linspace(0, 1, 121))
        errors.append(0.5 * (to_polyline(y, rec[f.step]).mean() + to_polyline(dense, y).mean()))
    assert np.mean(errors) < 0.006, errors
