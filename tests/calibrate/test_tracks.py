"""Offline tracking of a clip from the model-free start: close to the truth."""

import numpy as np

from calibrate.bags import read_clip
from calibrate.tracks import cut, track_clip
from deform import generic_model
from perception import load_config
from service.config import ServiceConfig

from .conftest import LENGTH, MASS, N


def test_tracking_a_clip_comes_within_a_few_millimetres_of_the_truth(clips):
    cfg = ServiceConfig(grippers=clips.grippers)
    clip = read_clip(clips.bags[1], cfg)
    track = track_clip(clip, generic_model(LENGTH, MASS, N), cfg.grippers, load_config(None))
    truth = clips.truths[1]
    assert track.positions.shape == truth.shape
    assert track.status["length_scale"] == 1.0  # the user's length, not the camera's
    err = np.linalg.norm(track.positions - truth, axis=-1)
    assert err.mean() < 0.004, err.mean(1)
    assert track.cloud_observed.shape == (15, N) and not track.cloud_observed[:, [0, 1, -2, -1]].any()
    assert track.coverage[2:-2].min() > 0.8
    rec = track.recording()
    assert rec.positions.shape == truth.shape and rec.dt == 0.01
    half = cut(track, 0, 70)
    assert half.n_frames == 70 and half.cloud_steps.max() < 70


def test_a_clip_is_tracked_at_the_given_length_even_where_the_camera_disagrees(clips):
    """Every clip at the user's one length (calibrate.checks compares it with the camera), where
    the service's tracker would take the camera's (perception/length.py)."""
    cfg = ServiceConfig(grippers=clips.grippers)
    clip = read_clip(clips.bags[1], cfg)
    model = generic_model(LENGTH, MASS, N)
    rest = model.rest_lengths().numpy().copy()
    rest[1:-1] *= 1.06
    track = track_clip(clip, model, cfg.grippers, load_config(None), rest=rest)
    assert track.status["length_scale"] == 1.0
    free = np.linalg.norm(np.diff(track.positions[-1], axis=0), axis=1)[1:-1].sum()
    assert abs(free / rest[1:-1].sum() - 1.0) < 0.01


def test_training_scores_the_track_where_and_when_a_cloud_corrected_it():
    """Track.recording: weights only at a cloud's step, at the vertices it corrected (never the
    gripped inputs); the scored targets are the track as corrected, the windows start smoothed."""
    from calibrate.tracks import Track

    T, n = 40, 6
    observed = np.zeros((3, n), dtype=bool)
    observed[0, 2] = observed[1, 3] = observed[2, 2] = True
    rng = np.random.default_rng(0)
    positions = rng.normal(size=(T, n, 3))
    track = Track("t", positions, np.zeros((T, 4, 3)), 0.01, np.array([0, 3, 20]), observed, (), {})
    w = track.at_clouds()
    assert w.shape == (T, n) and (w[:, [0, 1, -2, -1]] == 0).all()
    np.testing.assert_array_equal(np.flatnonzero(w[:, 2]), [0, 20])
    np.testing.assert_array_equal(np.flatnonzero(w[:, 3]), [3])
    rec = track.recording()
    np.testing.assert_array_equal(rec.weights, w)
    np.testing.assert_array_equal(rec.targets, positions)
    np.testing.assert_array_equal(rec.positions, track.smoothed())
    assert not np.allclose(rec.positions, positions)


def test_training_sees_the_track_without_the_sawtooth_of_its_corrections():
    """Track.smoothed: a motion tracked as prediction-then-jump at 30 Hz clouds comes back close to
    the motion; the gripped vertices stay as tracked; a smooth motion passes almost unchanged."""
    from calibrate.tracks import Track

    T, n, dt = 300, 6, 0.01
    t = np.arange(T) * dt
    motion = np.zeros((T, n, 3))
    motion[..., 2] = 0.05 * np.sin(2 * np.pi * 1.0 * t)[:, None]  # 1 Hz, 5 cm
    steps = np.arange(0, T, 3)  # a cloud every 3 steps
    lag = np.zeros((T, n, 3))  # the model lags the rope and each cloud takes the lag back
    for k in range(T):
        lag[k] = (k - steps[steps <= k][-1]) * 0.002
    tracked = motion - lag
    track = Track("t", tracked, np.zeros((T, 4, 3)), dt, steps, np.ones((len(steps), n), bool), (), {})
    out = track.smoothed()
    inner = slice(20, T - 20)  # away from the clip's ends
    free = [2, 3]
    raw_err = np.abs(tracked[inner][:, free] - motion[inner][:, free]).max()
    # jerks: the jumps are gone, what is left is an offset of half the lag
    assert (
        np.abs(np.diff(out[inner][:, free], 2, axis=0)).max()
        < 0.05 * np.abs(np.diff(tracked[inner][:, free], 2, axis=0)).max()
    )
    assert np.abs(out[inner][:, free] - motion[inner][:, free]).max() < raw_err
    np.testing.assert_array_equal(out[:, [0, 1, -2, -1]], tracked[:, [0, 1, -2, -1]])
    smooth = Track("s", motion, np.zeros((T, 4, 3)), dt, steps, np.ones((len(steps), n), bool), (), {})
    assert np.abs(smooth.smoothed()[inner] - motion[inner]).max() < 0.002  # 1 Hz passes (gain > 0.98)
    np.testing.assert_array_equal(smooth.recording().positions, smooth.smoothed())


def test_a_fast_motion_seen_by_a_15_hz_camera_keeps_its_amplitude():
    """A 3 Hz swing (the DEFORM motions' fastest) tracked with clouds 6-7 steps apart: the smoothed
    track keeps sinc^2(f T) = 0.88 of it (a Gaussian of one interval kept 0.45, which training read
    as damping)."""
    from calibrate.tracks import Track

    T, n, dt = 400, 6, 0.01
    t = np.arange(T) * dt
    motion = np.zeros((T, n, 3))
    motion[..., 0] = 0.05 * np.sin(2 * np.pi * 3.0 * t)[:, None]
    steps = np.unique(np.round(np.arange(0, 60) * 100 / 15).astype(int))
    steps = steps[steps < T]
    track = Track("t", motion, np.zeros((T, 4, 3)), dt, steps, np.ones((len(steps), n), bool), (), {})
    inner = slice(30, T - 30)
    kept = np.abs(track.smoothed()[inner, 2, 0]).max() / 0.05
    assert 0.84 < kept < 0.92, kept


def test_the_moving_average_of_a_sine_is_the_sine_times_sinc():
    from calibrate.tracks import moving_average

    t = np.arange(600.0)
    f = 1 / 40  # cycles per step
    for width in (3.0, 10.0 / 3.0, 6.5):
        out = moving_average(np.sin(2 * np.pi * f * t), width)
        expected = np.sinc(f * width) * np.sin(2 * np.pi * f * t)
        assert np.abs(out - expected)[20:-20].max() < 3e-3  # the samples joined linearly
    ramp = np.stack([t, -2 * t], axis=1)
    np.testing.assert_allclose(moving_average(ramp, 10.0 / 3.0)[5:-5], ramp[5:-5], atol=1e-9)
