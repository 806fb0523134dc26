"""Which way is up: the model's gravity is -z, and a rope held at both ends hangs along gravity.

Motion capture often exports y up (OptiTrack's default); read z up, such recordings would be fitted
under sideways gravity and every result would be nonsense, silently. The mean sag of the free
markers from the line between the gripped ones says which way the rope hangs.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from deform.io.recordings import Recording, RecordingError

UP_CHECK_MIN_SAG = 0.01  # [m] below this mean sag the direction says nothing (a taut or stiff rope)
# [deg] the most the mean sag may turn from -z; DEFORM's rods hang within 18 deg in every recording
UP_CHECK_MAX_ANGLE = 45.0


def mean_sag(recordings: list[Recording]) -> np.ndarray:
    """(3,) mean offset [m] of the free markers from the straight line between the gripped ones (at
    the same share of the arc length): a rope held at both ends hangs along gravity.

    Args:
        recordings: each ``positions`` (T, n, 3).

    Returns:
        The mean over recordings, frames and free markers.
    """
    out = []
    for r in recordings:
        x = r.positions
        n = x.shape[1]
        s = np.concatenate(
            [np.zeros((x.shape[0], 1)), np.cumsum(np.linalg.norm(np.diff(x, axis=1), axis=-1), 1)], 1
        )
        share = (s - s[:, 1:2]) / np.maximum(s[:, n - 2 : n - 1] - s[:, 1:2], 1e-9)
        chord = x[:, 1, None] + share[..., None] * (x[:, n - 2] - x[:, 1])[:, None]
        out.append((x - chord)[:, 2 : n - 2].mean(axis=(0, 1)))
    return np.mean(out, axis=0)


def check_up_axis(recordings: list[Recording], source: str | Path) -> str | None:
    """Raise when the rope clearly hangs sideways: the model's gravity is -z, and motion capture
    often exports y up (OptiTrack's default), which would make every fit nonsense. A rope bowing
    upward on average is only a warning: a stiff rod held in an arch does that with gravity along -z.

    Args:
        recordings: all recordings.
        source: where they came from, for the message.

    Returns:
        A warning, or None.

    Raises:
        RecordingError: naming the horizontal axis the rope hangs along.
    """
    sag = mean_sag(recordings)
    size = float(np.linalg.norm(sag))
    if size < UP_CHECK_MIN_SAG:
        return None
    angle = math.degrees(math.acos(max(-1.0, min(1.0, -sag[2] / size))))
    if angle <= UP_CHECK_MAX_ANGLE:
        return None
    axis = int(np.argmax(np.abs(sag)))
    along = f"{'+' if sag[axis] > 0 else '-'}{'xyz'[axis]}"
    if axis == 2:
        return (
            f"the rope bows upward on average (mean offset {size * 100:.1f} cm along +z from the line "
            "between its grippers): an arch, or recordings with gravity along +z (they are read z up)"
        )
    raise RecordingError(
        f"{source}: the rope hangs along {along} (mean sag {size * 100:.1f} cm, {angle:.0f} deg from -z); "
        "recordings are read z up, gravity along -z: rotate them (a y-up export?)"
    )
