r"""Recordings at another frame rate brought to the tool's 100 Hz.

The tool's windows, thresholds and material levels were calibrated on the DEFORM dataset's 100 Hz
frames (fit windows of 25 frames, one-second scoring windows of 100 frames, a recording's roll read
over 0.2 s, a delay in 10 ms frames). A recording at another rate is resampled to that rate on input
instead of rescaling every one of them: each marker coordinate is a cubic spline through its frames
(not-a-knot ends), evaluated every :data:`TOOL_DT` over the recording's own time span,

.. math:: x(k\,\Delta_{tool}),\quad k = 0 \dots \lfloor (T-1)\,\Delta / \Delta_{tool} \rfloor .

Why a spline: a rope's motion under gripper control lies well below the Nyquist rate of a 30 Hz
camera or motion-capture system, and a cubic follows it to second order between frames, where a
linear interpolation would put kinks in the velocities the fits start from. Faster recordings
(120, 240 Hz) are sampled at 100 Hz by the same spline; nothing the tool uses lies above 50 Hz.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import CubicSpline

from deform.io.recordings import DT, Recording

TOOL_DT = DT  # [s] the frame period the tool works at: the DEFORM dataset's


def resample(rec: Recording, dt: float, to_dt: float = TOOL_DT) -> Recording:
    """``rec``'s frames, taken every ``dt`` seconds, at every ``to_dt`` over the same time span.

    Args:
        rec: positions (T, n, 3), T >= 2.
        dt: its frame period [s].
        to_dt: the frame period wanted [s].

    Returns:
        The recording at ``to_dt`` (the same frames when the periods agree).
    """
    if math.isclose(dt, to_dt, rel_tol=1e-9):
        return Recording(name=rec.name, positions=rec.positions, dt=to_dt)
    t = np.arange(rec.n_frames) * dt
    frames = math.floor(float(t[-1]) / to_dt + 1e-9) + 1
    spline = CubicSpline(t, rec.positions, axis=0, bc_type="not-a-knot")
    return Recording(name=rec.name, positions=spline(np.arange(frames) * to_dt), dt=to_dt)
