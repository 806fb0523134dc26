"""Reading recordings safely: DEFORM pickles are untrusted input."""
from deform.io.safe_pickle import UnsafePickleError, safe_load_pickle
from deform.io.recordings import (
    Recording,
    RecordingError,
    find_data_root,
    load_recording,
    load_recordings,
    save_recording,
)

__all__ = [
    "UnsafePickleError",
    "safe_load_pickle",
    "Recording",
    "RecordingError",
    "find_data_root",
    "load_recording",
    "load_recordings",
    "save_recording",
]
