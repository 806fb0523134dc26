"""Reading recordings safely: DEFORM pickles are untrusted input."""

from deform.io.recordings import (
    Recording,
    RecordingError,
    find_data_root,
    load_recording,
    load_recordings,
    save_recording,
)
from deform.io.safe_pickle import UnsafePickleError, safe_load_pickle

__all__ = [
    "Recording",
    "RecordingError",
    "UnsafePickleError",
    "find_data_root",
    "load_recording",
    "load_recordings",
    "safe_load_pickle",
    "save_recording",
]
