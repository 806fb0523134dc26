r"""Marker noise measured from the recordings, and smoothing when it is far above the calibrated level.

Every fit window starts from two recorded frames, so white marker noise of :math:`\sigma` per
coordinate puts :math:`\sqrt{2}\,\sigma/\Delta t` into each starting velocity (0.14 m/s at 1 mm and
100 Hz). The tool's thresholds and material levels were calibrated on recordings with 0.3 mm of
noise (the benchmarks'; real motion capture measures about 0.03 mm frame to frame, DEFORM's DLO1-5).
At 1 mm a bending-rate damping that removes the noise in the start was named on a stiff control
(docs/diagnose.md). So the tool measures the noise and, only when it is well above the calibrated
level (:data:`SMOOTH_ABOVE_M`), smooths the recordings as much as makes frame-to-frame velocities
most accurate.

Noise estimate: the k-th difference of white noise has variance :math:`\binom{2k}{k}\sigma^2`, while
a rope's motion under gripper control, sampled at 100 Hz, contributes little to the 4th difference
(0.01-0.08 mm on noise-free simulated ropes, benchmarks/marker_noise.py). With a median absolute deviation, rare tracking
spikes do not count:

.. math:: \hat\sigma = 1.4826\,\mathrm{MAD}(\Delta^4 x) / \sqrt{70} .

Smoothing: a quadratic Savitzky-Golay filter (scipy) of w frames, w chosen to minimise the
estimated mean squared error of the velocities :math:`\Delta y`, bias plus noise,

.. math:: R(w) = \max\big(\overline{(\Delta y - \Delta x)^2} - \hat\sigma^2 \|k_w - k_1\|^2,\,0\big)
          + \hat\sigma^2 \|k_w\|^2 ,

where :math:`k_w` is the filter's first-difference kernel (:math:`k_1 = (-1, 1)`, the raw
difference, :math:`R(1) = 2\hat\sigma^2`). The first term estimates the bias the smoothing puts
into the rope's own motion from the data themselves, so a fast, light rope is smoothed less than a
slow, stiff one. Why Savitzky-Golay: a local quadratic keeps a velocity and an acceleration
unbiased, which is what a start state needs, where a low-pass filter would delay them.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import savgol_coeffs, savgol_filter

from deform.io.recordings import Recording

CALIBRATED_NOISE_M = 0.3e-3  # the marker noise the tool's thresholds were calibrated at (benchmarks)
SMOOTH_ABOVE_M = 0.5e-3  # smooth only above this estimate: real capture and the benchmarks stay raw
MAX_WINDOW = 21  # frames: 0.2 s at 100 Hz, beyond which a quadratic no longer follows a rope's swing
_DIFF_ORDER = 4


def marker_noise(recordings: list[Recording]) -> float:
    r"""White marker noise per coordinate [m]: the median over recordings of :math:`\hat\sigma` of
    the free markers (the gripped ones may be smoothed by a robot's own state estimate).

    Args:
        recordings: each ``positions`` (T, n, 3), T > 4.

    Returns:
        The estimate [m].
    """
    scale = 1.4826 / math.sqrt(math.comb(2 * _DIFF_ORDER, _DIFF_ORDER))
    per = []
    for r in recordings:
        d = np.diff(r.positions[:, 2:-2], n=_DIFF_ORDER, axis=0).ravel()
        per.append(scale * float(np.median(np.abs(d - np.median(d)))))
    return float(np.median(per))


def velocity_noise_gain(window: int) -> float:
    r"""Variance of a first difference of the smoothed signal over that of the raw one, for white
    noise, away from the ends: :math:`\tfrac12 \|k_w\|^2`.

    Args:
        window: odd window length (1: no smoothing).

    Returns:
        The gain (1 for no smoothing).
    """
    return 0.5 * float(np.sum(_difference_kernel(window) ** 2))


def _difference_kernel(window: int) -> np.ndarray:
    r"""Weights of :math:`y_{t+1} - y_t` on :math:`x_{t-m} \dots x_{t+m+1}` for the filter's output y
    (``window`` = 1: the raw difference)."""
    h = savgol_coeffs(window, 2) if window > 1 else np.ones(1)
    return -np.diff(np.concatenate([[0.0], h, [0.0]]))  # h is symmetric


def smoothing_risk(recordings: list[Recording], sigma: float, window: int) -> float:
    r""":math:`R(w)`: the estimated mean squared frame-to-frame displacement error [m^2] after
    smoothing with ``window`` frames (1: raw), over the free markers away from the ends.

    Args:
        recordings: the recordings.
        sigma: their marker noise [m].
        window: odd window (1 for none).

    Returns:
        Bias squared plus noise variance.
    """
    if window == 1:
        return 2.0 * sigma**2
    k = _difference_kernel(window)
    m = window // 2
    raw = np.zeros_like(k)
    raw[m : m + 2] = _difference_kernel(1)  # the raw difference, aligned with k
    mse = []
    for r in recordings:
        x = r.positions[:, 2:-2]
        d = np.diff(savgol_filter(x, window, 2, axis=0, mode="interp"), axis=0) - np.diff(x, axis=0)
        mse.append(float(np.mean(d[m : len(d) - m] ** 2)))
    bias2 = max(float(np.mean(mse)) - sigma**2 * float(np.sum((k - raw) ** 2)), 0.0)
    return bias2 + sigma**2 * float(np.sum(k**2))


def smoothing_window(recordings: list[Recording], sigma: float) -> int | None:
    """The window of least :func:`smoothing_risk` among 5 ... :data:`MAX_WINDOW` frames and none;
    None also when ``sigma`` is at most :data:`SMOOTH_ABOVE_M` (the recordings stay as calibrated).

    Args:
        recordings: the recordings.
        sigma: their marker noise [m].

    Returns:
        The window in frames, or None.
    """
    if sigma <= SMOOTH_ABOVE_M:
        return None
    risks = {w: smoothing_risk(recordings, sigma, w) for w in (1, *range(5, MAX_WINDOW + 1, 2))}
    best = min(risks, key=risks.get)
    return None if best == 1 else best


def smooth(rec: Recording, window: int) -> Recording:
    """``rec`` smoothed along time by a quadratic Savitzky-Golay filter of ``window`` frames (the
    ends by the polynomial fitted to the first and last window).

    Args:
        rec: positions (T, n, 3) with T >= window.
        window: odd length.

    Returns:
        The smoothed recording.
    """
    pos = savgol_filter(rec.positions, window, 2, axis=0, mode="interp")
    return Recording(name=rec.name, positions=pos, dt=rec.dt)


def denoise(recordings: list[Recording]) -> tuple[list[Recording], str | None]:
    """The recordings, smoothed when their marker noise is above :data:`SMOOTH_ABOVE_M` and a
    window lowers :func:`smoothing_risk`, and the report's warning saying so (None when they are
    returned as given).

    Args:
        recordings: all of a diagnosis's recordings (fit and check, one rate).

    Returns:
        ``(recordings, warning)``.
    """
    sigma = marker_noise(recordings)
    window = smoothing_window(recordings, sigma)
    if window is None:
        return recordings, None
    gain = velocity_noise_gain(window)
    note = (
        f"marker noise about {sigma * 1e3:.2f} mm (above {SMOOTH_ABOVE_M * 1e3:.1f} mm, the tool was calibrated "
        f"at {CALIBRATED_NOISE_M * 1e3:.1f} mm): recordings smoothed by a {window}-frame quadratic "
        f"Savitzky-Golay filter (the noise in frame-to-frame velocities x{math.sqrt(gain):.2f}); "
        "--denoise off keeps them raw"
    )
    return [smooth(r, window) for r in recordings], note
