"""Marker dropouts: short gaps filled in time, what cannot be filled said plainly.

Motion capture loses a marker whenever the gripper or the rope itself hides it, and exports the
frame with NaN for it. A rope moves smoothly over a tenth of a second, so a short gap is filled by a
cubic spline through that marker's own trajectory; a longer one would be invented motion, and is an
error. Frames before the first and after the last complete frame cannot be interpolated and are
dropped.

Written here rather than taken from a library: the interpolation is scipy's ``CubicSpline``; what is
this project's own is the policy (per marker, a bound on the gap, trimming the ends, one-line errors
naming the file and the marker).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deform.io.recordings import Recording, RecordingError

MAX_GAP_S = 0.1  # the longest dropout filled by default [s]


@dataclass(frozen=True)
class FilledGaps:
    """What :func:`fill_gaps` did to one recording."""

    filled: int  # marker-frames filled
    longest: int  # the longest filled gap [frames]
    trimmed_start: int  # frames dropped before the first complete frame
    trimmed_end: int  # frames dropped after the last complete frame

    @property
    def changed(self) -> bool:
        return bool(self.filled or self.trimmed_start or self.trimmed_end)


def _runs(missing: np.ndarray) -> list[tuple[int, int]]:
    """``(start, length)`` of each run of True in a 1-D bool array."""
    edges = np.diff(np.concatenate([[0], missing.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(a), int(b - a)) for a, b in zip(starts, ends)]


def fill_gaps(positions: np.ndarray, dt: float, name: str, max_gap_s: float = MAX_GAP_S):
    """Fill each marker's short dropouts by a cubic spline in time; drop incomplete end frames.

    Args:
        positions: (T, n, 3) [m], NaN where a marker was not seen (a marker with any NaN coordinate
            in a frame counts as missing there).
        dt: frame period [s].
        name: the recording's name, for messages.
        max_gap_s: the longest gap filled [s]; 0 fills nothing.

    Returns:
        ``(positions, FilledGaps)``: (T', n, 3) with no NaN, T' = T less the trimmed frames.

    Raises:
        RecordingError: no complete frame, or a gap longer than ``max_gap_s`` (the message names
            the marker, the frames and the bound).
    """
    from scipy.interpolate import CubicSpline  # scipy's import is slow; only recordings with gaps need it

    missing = np.isnan(positions).any(axis=-1)  # (T, n)
    if not missing.any():
        return positions, FilledGaps(0, 0, 0, 0)
    complete = np.flatnonzero(~missing.any(axis=1))
    if complete.size == 0:
        raise RecordingError(f"{name}: no frame has every marker")
    first, last = int(complete[0]), int(complete[-1])
    x = positions[first : last + 1].copy()
    missing = missing[first : last + 1]
    max_frames = int(np.floor(max_gap_s / dt + 1e-9))
    t = np.arange(x.shape[0], dtype=np.float64)
    filled, longest = 0, 0
    for j in np.flatnonzero(missing.any(axis=0)):
        runs = _runs(missing[:, j])
        start, length = max(runs, key=lambda r: r[1])
        if length > max_frames:
            raise RecordingError(
                f"{name}: marker {j} is missing for {length} frames from frame {first + start} "
                f"({length * dt:.3g} s; gaps up to {max_gap_s:g} s are filled, see --max-gap)"
            )
        seen = ~missing[:, j]
        x[~seen, j] = CubicSpline(t[seen], x[seen, j], axis=0)(t[~seen])
        filled += int((~seen).sum())
        longest = max(longest, length)
    return x, FilledGaps(filled, longest, first, positions.shape[0] - 1 - last)


def fill_recordings(
    recordings: list[Recording], max_gap_s: float = MAX_GAP_S, dt: float | None = None
) -> tuple[list[Recording], str | None]:
    """:func:`fill_gaps` on each recording, and one line saying what was done (None when every
    recording was complete).

    Args:
        recordings: loaded with ``allow_gaps=True``.
        max_gap_s: the longest gap filled [s].
        dt: the frame period [s] (None: each recording's own; a pickle does not hold it, so a caller
            that knows it better passes it).

    Returns:
        ``(recordings, note)``.

    Raises:
        RecordingError: see :func:`fill_gaps`.
    """
    out, done = [], []
    for r in recordings:
        x, gaps = fill_gaps(r.positions, dt or r.dt, r.name, max_gap_s)
        out.append(Recording(name=r.name, positions=x, dt=r.dt) if gaps.changed else r)
        if gaps.changed:
            done.append((r.name, gaps))
    if not done:
        return out, None
    note = (
        f"markers not seen (NaN) in {len(done)} recording(s) {[name for name, _ in done]}: "
        f"{sum(g.filled for _, g in done)} marker-frame(s) filled by cubic splines in time (gaps of at "
        f"most {max(g.longest for _, g in done)} frames)"
    )
    trimmed = sum(g.trimmed_start + g.trimmed_end for _, g in done)
    if trimmed:
        note += f", {trimmed} incomplete frame(s) at the recordings' ends dropped"
    return out, note
