"""Marker noise measured from recordings, and smoothing only far above the calibrated level."""

import json

import numpy as np
import pytest

from deform.diagnose.denoise import (
    SMOOTH_ABOVE_M,
    denoise,
    marker_noise,
    smooth,
    smoothing_risk,
    smoothing_window,
    velocity_noise_gain,
)
from deform.diagnose.spec import load_inputs
from deform.io import save_recording
from deform.io.recordings import Recording

DT = 0.01


def swinging_rope(seed: int, frames: int = 300, n: int = 10, hz: float = 1.0) -> np.ndarray:
    """(T, n, 3) a smooth rope-like motion: each marker a sum of three sinusoids around ``hz``,
    amplitudes of 5-10 cm."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None, None] * DT
    out = np.zeros((frames, n, 3))
    for _ in range(3):
        f = hz * rng.uniform(0.5, 2.0)
        amp = rng.uniform(0.05, 0.1, size=(1, n, 3))
        phase = rng.uniform(0, 2 * np.pi, size=(1, n, 3))
        out += amp * np.sin(2 * np.pi * f * t + phase)
    return out


def recordings(noise_m: float, hz: float = 1.0, count: int = 6, seed: int = 0):
    clean = [swinging_rope(seed + i, hz=hz) for i in range(count)]
    rng = np.random.default_rng(100 + seed)
    noisy = [Recording(f"r{i}", c + rng.normal(0, noise_m, c.shape)) for i, c in enumerate(clean)]
    return clean, noisy


def velocity_error(recs, clean, ends: int = 0) -> float:
    """RMS error of frame-to-frame displacements of the free markers [m], ``ends`` frames left out
    at each end."""
    d = [
        (np.diff(r.positions, axis=0) - np.diff(c, axis=0))[ends : len(c) - 1 - ends, 2:-2]
        for r, c in zip(recs, clean)
    ]
    return float(np.sqrt(np.mean(np.concatenate(d) ** 2)))


@pytest.mark.parametrize("noise_mm", [0.3, 1.0, 2.0])
def test_marker_noise_is_measured_within_ten_percent_and_ignores_tracking_spikes(noise_mm):
    _, noisy = recordings(noise_mm * 1e-3)
    spiked = []
    for r in noisy:  # 0.05 % of the points jump by 5 cm, as rare tracking glitches do
        p = r.positions.copy()
        idx = np.random.default_rng(1).choice(p.size, max(1, p.size // 2000), replace=False)
        p.reshape(-1)[idx] += 0.05
        spiked.append(Recording(r.name, p))
    for recs in (noisy, spiked):
        assert marker_noise(recs) == pytest.approx(noise_mm * 1e-3, rel=0.1)


def test_velocity_noise_gain_is_what_white_noise_shows():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((4000, 1, 1))
    from scipy.signal import savgol_filter

    for w in (1, 5, 7, 11):
        y = x if w == 1 else savgol_filter(x, w, 2, axis=0)
        measured = np.var(np.diff(y[20:-20], axis=0)) / 2.0
        assert velocity_noise_gain(w) == pytest.approx(measured, rel=0.1), w
    assert velocity_noise_gain(1) == 1.0


def test_recordings_at_the_calibrated_noise_are_returned_as_given():
    # every benchmark row (0.3 mm) and real capture (0.03 mm) must reach the fits unchanged
    _, noisy = recordings(0.3e-3)
    assert marker_noise(noisy) < SMOOTH_ABOVE_M
    out, note = denoise(noisy)
    assert note is None and all(a is b for a, b in zip(out, noisy))


def test_smoothing_a_noisy_rope_brings_its_velocities_closer_to_the_clean_ones():
    clean, noisy = recordings(1e-3)
    out, note = denoise(noisy)
    assert note is not None and "Savitzky-Golay" in note and "--denoise off" in note
    assert velocity_error(out, clean) < 0.5 * velocity_error(noisy, clean)


def test_the_risk_estimate_follows_the_true_error_so_a_fast_rope_is_smoothed_less():
    sigma = 1e-3
    windows = {}
    for hz in (0.5, 2.0):
        clean, noisy = recordings(sigma, hz=hz)
        for w in (1, 5, 9, 15):
            smoothed = [smooth(r, w) for r in noisy] if w > 1 else noisy
            true = velocity_error(smoothed, clean, ends=w // 2)  # the estimate leaves the ends out
            est = np.sqrt(smoothing_risk(noisy, marker_noise(noisy), w))
            assert est == pytest.approx(true, rel=0.25), (hz, w, est, true)
        windows[hz] = smoothing_window(noisy, marker_noise(noisy))
    assert windows[0.5] is not None and (windows[2.0] is None or windows[2.0] < windows[0.5]), windows


def _write(tmp_path, recs, dt: float):
    for name, part in (("fit", recs[:4]), ("check", recs[4:])):
        (tmp_path / name).mkdir()
        for i, r in enumerate(part):
            save_recording(tmp_path / name / f"{i:02d}.pkl", r.positions)
    rod = tmp_path / "rod.json"
    span = float(np.median(np.linalg.norm(np.diff(recs[0].positions, axis=1), axis=-1).sum(-1)))
    rod.write_text(json.dumps({"length_m": span, "mass_kg": 0.05, "n_vertices": 10, "dt": dt}))
    return rod


def test_load_inputs_smooths_noisy_100_hz_recordings_and_says_so_unless_told_not_to(tmp_path):
    _, noisy = recordings(1e-3)
    rod = _write(tmp_path, noisy, DT)
    smoothed = load_inputs(rod, tmp_path / "fit", tmp_path / "check")
    assert any("Savitzky-Golay" in w for w in smoothed.warnings)
    assert not np.allclose(smoothed.fit[0].positions, noisy[0].positions)
    raw = load_inputs(rod, tmp_path / "fit", tmp_path / "check", smooth_noise=False)
    assert not any("Savitzky-Golay" in w for w in raw.warnings)
    np.testing.assert_array_equal(raw.fit[0].positions, noisy[0].positions)
    np.testing.assert_array_equal(raw.check[0].positions, noisy[4].positions)


def test_recordings_slower_than_100_hz_are_not_smoothed(tmp_path):
    # at 50 Hz a rope's own motion fills the 4th difference the noise is measured from
    _, noisy = recordings(1e-3)
    rod = _write(tmp_path, noisy, 0.02)
    inputs = load_inputs(rod, tmp_path / "fit", tmp_path / "check")
    assert not any("Savitzky-Golay" in w for w in inputs.warnings)


def test_the_cli_smooths_by_default_and_not_with_denoise_off(tmp_path, monkeypatch):
    import deform.diagnose.selection as selection
    from deform.cli import main

    _, noisy = recordings(1e-3)
    rod = _write(tmp_path, noisy, DT)
    seen = []

    def fake_diagnose(inputs, budget, start_model=None, workers=1):  # stop before any fitting
        seen.append(inputs.warnings)
        raise SystemExit(0)

    monkeypatch.setattr(selection, "diagnose", fake_diagnose)
    for extra in ([], ["--denoise", "off"]):
        with pytest.raises(SystemExit):
            main(["diagnose", "--rod", str(rod), "--fit", str(tmp_path / "fit"), "--check", str(tmp_path / "check"),
                  "--out", str(tmp_path / "out"), *extra])  # fmt: skip
    assert [any("Savitzky-Golay" in w for w in ws) for ws in seen] == [True, False]
