import os
import pickle

import numpy as np
import pytest

from deform.io.recordings import RecordingError, load_recording, load_recordings, save_recording
from deform.io.safe_pickle import UnsafePickleError, safe_load_pickle


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned > /tmp/deform_pwned",))


def _frames(T=10, n=7):
    return [np.random.default_rng(0).normal(size=(3, n)) for _ in range(T)]


def test_round_trip_and_vertex_major_layout(tmp_path):
    frames = _frames()
    path = tmp_path / "a.pkl"
    path.write_bytes(pickle.dumps(frames))
    rec = load_recording(path)
    assert rec.positions.shape == (10, 7, 3)
    assert np.array_equal(rec.positions[3, 5], frames[3][:, 5])
    save_recording(tmp_path / "b.pkl", rec.positions)
    assert np.array_equal(load_recording(tmp_path / "b.pkl").positions, rec.positions)


def test_plain_lists_are_accepted(tmp_path):
    path = tmp_path / "a.pkl"
    path.write_bytes(pickle.dumps([f.tolist() for f in _frames()]))
    assert load_recording(path).positions.shape == (10, 7, 3)


def test_hostile_pickle_is_refused_without_running_code(tmp_path):
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps([_Evil()]))
    if os.path.exists("/tmp/deform_pwned"):
        os.remove("/tmp/deform_pwned")
    with pytest.raises(RecordingError, match=r"evil\.pkl.*posix\.system|evil\.pkl.*os\.system"):
        load_recording(path)
    assert not os.path.exists("/tmp/deform_pwned")
    with pytest.raises(UnsafePickleError):
        safe_load_pickle(pickle.dumps({"a": 1}.__class__))


@pytest.mark.parametrize(
    "payload, message",
    [
        (b"not a pickle", "malformed pickle"),
        (pickle.dumps({"x": 1}), "expected a list"),
        (pickle.dumps([np.zeros((4, 7))] * 5), r"shape \(3, n\)"),
        (pickle.dumps([np.full((3, 7), np.nan)] * 5), "NaN"),
        (pickle.dumps([np.zeros((3, 7))]), "at least 3 frames"),
    ],
)
def test_malformed_files_name_the_file_and_problem(tmp_path, payload, message):
    path = tmp_path / "bad.pkl"
    path.write_bytes(payload)
    with pytest.raises(RecordingError, match=message) as err:
        load_recording(path)
    assert "bad.pkl" in str(err.value)


def test_directory_checks(tmp_path):
    with pytest.raises(RecordingError, match=r"no \.pkl"):
        load_recordings(tmp_path)
    (tmp_path / "a.pkl").write_bytes(pickle.dumps(_frames(n=7)))
    (tmp_path / "b.pkl").write_bytes(pickle.dumps(_frames(n=8)))
    with pytest.raises(RecordingError, match="different marker counts"):
        load_recordings(tmp_path)
    with pytest.raises(RecordingError, match="has 7 markers, the rod has 13"):
        load_recordings(tmp_path, n_vertices=13)


def test_real_recording_loads(data_root):
    rec = load_recording(data_root / "DLO1" / "eval" / "100.pkl")
    assert rec.positions.shape == (500, 13, 3)
