"""Marker dropouts: short gaps filled close to the true motion, long ones and infinities refused."""

import pickle

import numpy as np
import pytest

from deform.io.gaps import fill_gaps
from deform.io.recordings import RecordingError, load_recording


def _swinging(T=120, n=8, dt=0.01):
    """A rope-like smooth motion: markers on a line swinging and sagging at 1-2 Hz."""
    t = np.arange(T)[:, None] * dt
    s = np.linspace(0, 1, n)[None, :]
    x = np.stack(
        [
            0.6 * s + 0.02 * np.sin(2 * np.pi * 1.3 * t),
            0.05 * np.sin(np.pi * s) * np.cos(2 * np.pi * t),
            0.3 - 0.08 * np.sin(np.pi * s) + 0 * t,
        ],
        axis=-1,
    )
    return x


def test_a_short_gap_is_filled_close_to_the_motion_and_nothing_else_changes():
    truth = _swinging()
    x = truth.copy()
    x[40:48, 3] = np.nan  # 8 frames, 80 ms
    x[70, 5, 1] = np.nan  # one coordinate lost: the marker counts as missing there
    filled, gaps = fill_gaps(x, 0.01, "rec")
    assert not np.isnan(filled).any() and filled.shape == truth.shape
    assert gaps.filled == 9 and gaps.longest == 8 and (gaps.trimmed_start, gaps.trimmed_end) == (0, 0)
    assert np.abs(filled - truth).max() < 2e-4  # 0.2 mm on motion of centimetres
    seen = ~np.isnan(x).any(-1)
    assert np.array_equal(filled[seen], truth[seen])


def test_incomplete_end_frames_are_dropped_not_extrapolated():
    x = _swinging()
    x[:3, 2] = np.nan
    x[-5:, 0] = np.nan
    filled, gaps = fill_gaps(x, 0.01, "rec")
    assert filled.shape[0] == x.shape[0] - 8 and (gaps.trimmed_start, gaps.trimmed_end) == (3, 5)
    assert np.array_equal(filled, x[3:-5])


def test_a_gap_longer_than_the_bound_is_an_error_naming_marker_and_frames():
    x = _swinging()
    x[50:70, 4] = np.nan  # 0.2 s
    with pytest.raises(RecordingError, match=r"rec: marker 4 is missing for 20 frames from frame 50"):
        fill_gaps(x, 0.01, "rec")
    filled, _ = fill_gaps(x, 0.01, "rec", max_gap_s=0.25)
    assert not np.isnan(filled).any()
    one = _swinging()
    one[7, 4] = np.nan
    with pytest.raises(RecordingError, match="marker 4 is missing for 1 frames"):
        fill_gaps(one, 0.01, "rec", max_gap_s=0.0)  # 0: nothing is filled
    everywhere = _swinging()
    everywhere[::2, 1] = np.nan
    everywhere[1::2, 2] = np.nan
    with pytest.raises(RecordingError, match="no frame has every marker"):
        fill_gaps(everywhere, 0.01, "rec")


def test_loading_keeps_nan_only_when_asked_and_never_infinity(tmp_path):
    frames = [f.T.copy() for f in _swinging(T=10)]
    frames[4][2, 3] = np.nan
    path = tmp_path / "gap.pkl"
    path.write_bytes(pickle.dumps(frames))
    with pytest.raises(RecordingError, match="NaN"):
        load_recording(path)
    assert np.isnan(load_recording(path, allow_gaps=True).positions[4, 3, 2])
    frames[4][2, 3] = np.inf
    path.write_bytes(pickle.dumps(frames))
    with pytest.raises(RecordingError, match="infinite"):
        load_recording(path, allow_gaps=True)
