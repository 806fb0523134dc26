"""Segmentation: the rope's colour spilled onto what lies behind it (a real sensor's colour registered off
its depth, mixed depth pixels at edges) is not taken for rope."""

from dataclasses import replace

import numpy as np
import pytest

from perception import load_config, render_recording
from perception.polyline import segment_distances
from perception.segment import colour_mask, front_surface, segment_rope


def test_front_surface_drops_pixels_behind_the_rope_beside_them():
    z = np.full((12, 12), np.nan)
    mask = np.zeros((12, 12), dtype=bool)
    z[:, 3:6], mask[:, 3:6] = 1.0, True  # the rope, 1 m away
    z[:, 6:8], mask[:, 6:8] = 1.4, True  # its colour on the table 40 cm behind
    z[:, 8:] = 1.4
    z[5, 4] = 1.03  # rope noise within the margin stays
    keep = front_surface(z, mask, window=2, margin=0.05)
    assert keep[:, 3:6].all() and not keep[:, 6:].any()
    # a window of 0 compares each pixel with itself: nothing dropped; nothing outside the mask kept
    assert np.array_equal(front_surface(z, mask, window=0, margin=0.05), mask)
    assert not front_surface(z, np.zeros_like(mask), window=2, margin=0.05).any()


@pytest.fixture(scope="module")
def sensor_frame(recording):
    """One cloud with colour registered 3 px off the depth and every far edge pixel a mixed pixel."""
    cfg = load_config()
    cfg = replace(cfg, render=replace(cfg.render, color_shift_px=3, flying_pixels=1.0))
    return render_recording(recording.positions, steps=[60], config=cfg, seed=4)[0], recording.positions[60]


def _far(points_cam, frame, truth) -> float:
    """Share of the points more than 3 cm from the true rope."""
    d = segment_distances(frame.camera.to_world(points_cam), truth)
    return float(np.mean(d > 0.03))


def test_spilled_colour_is_not_rope(sensor_frame):
    frame, truth = sensor_frame
    seg = load_config().segmentation
    assert seg.spill_window > 0
    off = segment_rope(frame.xyz, frame.rgb, replace(seg, spill_window=0))
    on = segment_rope(frame.xyz, frame.rgb, seg)
    far_off, far_on = _far(off, frame, truth), _far(on, frame, truth)
    assert far_off > 0.05  # the sensor's artefacts are there without the filter
    assert far_on < 0.25 * far_off  # what is left: mixed pixels within the margin of the rope
    near_off = np.sum(segment_distances(frame.camera.to_world(off), truth) <= 0.03)
    assert len(on) * (1 - far_on) > 0.95 * near_off  # the rope itself stays


def test_clean_clouds_keep_their_rope(clear_frames):
    seg = load_config().segmentation
    for f in clear_frames[::5]:
        on = segment_rope(f.xyz, f.rgb, seg)
        off = segment_rope(f.xyz, f.rgb, replace(seg, spill_window=0))
        assert len(on) >= 0.98 * len(off)


def test_a_background_of_zeros_keeps_the_rope(clear_frames):
    """A camera (RealSense's ordered clouds) or renderer that writes a pixel without depth as (0, 0, 0):
    the rope beside those pixels is the same rope as beside NaN ones. Where the depth of a rope pixel
    dropped out, its colour stays; a zero read as its depth would be rope at the lens, in front of
    every rope pixel around it."""
    seg = load_config().segmentation
    rng = np.random.default_rng(0)
    for f in clear_frames[::10]:
        rope = colour_mask(f.rgb.reshape(-1, 3), seg).reshape(f.rgb.shape[:2])
        dropped = rope & (rng.random(rope.shape) < 0.2)  # a fifth of the rope's depth lost
        nan = np.where(dropped[..., None], np.nan, f.xyz).astype(np.float32)
        zeros = np.where(np.isfinite(nan).all(-1, keepdims=True), nan, 0.0).astype(np.float32)
        assert dropped.sum() > 5 and (zeros == 0).all(-1).mean() > 0.1
        kept = segment_rope(nan, f.rgb, seg)
        assert len(kept) > 0.6 * rope.sum()
        np.testing.assert_array_equal(segment_rope(zeros, f.rgb, seg), kept)
