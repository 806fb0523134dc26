"""DEFORM recordings: 100 Hz marker trajectories of a rod held at both ends.

A file is a pickle of T arrays of shape (3, n) (x, y, z in metres). In memory a recording is an
array of shape (T, n, 3), vertex-major, which is what the model consumes.
"""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from deform.io.safe_pickle import UnsafePickleError, safe_load_pickle

DT = 0.01  # the recordings are 100 Hz


class RecordingError(ValueError):
    """A recording file or directory that cannot be used; the message names the file."""


@dataclass(frozen=True)
class Recording:
    name: str
    positions: np.ndarray  # (T, n, 3) float64, metres, z up
    dt: float = DT
    # (T, n) how much each position is to be trusted in training's loss, 0..1 (None: all fully): a
    # camera track's vertices that no cloud showed were filled in by the tracker's model
    weights: np.ndarray | None = None
    # (T, n, 3) what a prediction is scored against where ``weights`` > 0 (None: ``positions``), while
    # windows start from ``positions``: a camera track is scored at the clouds, as corrected, but
    # started from its smoothed states (calibrate.tracks)
    targets: np.ndarray | None = None

    @property
    def scored(self) -> np.ndarray:
        """(T, n, 3) what a prediction is scored against: ``targets``, else ``positions``."""
        return self.positions if self.targets is None else self.targets

    @property
    def n_vertices(self) -> int:
        return self.positions.shape[1]

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @cached_property
    def reference_frames(self) -> np.ndarray:
        """(T, n-1, 3) reference directors an open-loop rollout from frame 0 carries at each frame
        (:func:`deform.rod.geometry.transported_frames`): where a window cut from this recording starts."""
        import torch

        from deform.rod.geometry import transported_frames

        return transported_frames(torch.as_tensor(self.positions, dtype=torch.float64)).numpy()


def find_data_root() -> Path | None:
    """`DEFORM_DATA`, else `../shared/data/deform` beside the project (or the cwd); None when the
    directory does not exist (then everything runs on generated recordings)."""
    env = os.environ.get("DEFORM_DATA")
    if env:
        return Path(env) if Path(env).is_dir() else None
    here = Path(__file__).resolve().parents[2]
    for base in (here, Path.cwd()):
        candidate = base.parent / "shared" / "data" / "deform"
        if candidate.is_dir():
            return candidate
    return None


def _to_array(obj, path: Path, allow_gaps: bool = False) -> np.ndarray:
    if not isinstance(obj, (list, tuple, np.ndarray)):
        raise RecordingError(f"{path}: expected a list of (3, n) frames, got {type(obj).__name__}")
    try:
        arr = np.asarray(obj, dtype=np.float64)
    except (ValueError, TypeError) as exc:
        raise RecordingError(f"{path}: frames are not a regular numeric array ({exc})") from None
    if arr.ndim != 3 or arr.shape[1] != 3:
        raise RecordingError(f"{path}: expected frames of shape (3, n), got array of shape {arr.shape}")
    if arr.shape[0] < 3:
        raise RecordingError(f"{path}: needs at least 3 frames, has {arr.shape[0]}")
    if arr.shape[2] < 5:
        raise RecordingError(f"{path}: needs at least 5 markers, has {arr.shape[2]}")
    if np.isinf(arr).any():
        bad = int(np.isinf(arr).any(axis=(1, 2)).sum())
        raise RecordingError(f"{path}: {bad} frame(s) contain infinite values")
    if not allow_gaps and np.isnan(arr).any():
        bad = int(np.isnan(arr).any(axis=(1, 2)).sum())
        raise RecordingError(f"{path}: {bad} frame(s) contain NaN (markers not seen)")
    return np.ascontiguousarray(arr.transpose(0, 2, 1))


def load_recording(path: str | Path, n_vertices: int | None = None, allow_gaps: bool = False) -> Recording:
    """Load one DEFORM pickle safely and validate it.

    Args:
        path: a ``.pkl`` of the DEFORM format: a list of (3, n) arrays, one per frame [m].
        n_vertices: the marker count the caller expects (None: any).
        allow_gaps: keep NaN (markers not seen) for the caller to fill (:mod:`deform.io.gaps`);
            False: NaN is an error.

    Returns:
        A :class:`Recording` with ``positions`` (T, n, 3) float64.

    Raises:
        RecordingError: missing file, a pickle holding anything but lists and numpy arrays,
            wrong shapes, NaNs, or another marker count; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    try:
        obj = safe_load_pickle(path)
    except UnsafePickleError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    positions = _to_array(obj, path, allow_gaps)
    if n_vertices is not None and positions.shape[1] != n_vertices:
        raise RecordingError(f"{path}: has {positions.shape[1]} markers, the rod has {n_vertices}")
    return Recording(name=path.stem, positions=positions)


def load_recordings(
    directory: str | Path, n_vertices: int | None = None, allow_gaps: bool = False
) -> list[Recording]:
    """Every .pkl in a directory, sorted by name (numerically: 2 before 10).

    Args:
        directory: a folder of DEFORM pickles.
        n_vertices: the marker count every recording must have (None: the same in all).
        allow_gaps: see :func:`load_recording`.

    Returns:
        The recordings, each ``positions`` (T, n, 3).

    Raises:
        RecordingError: not a directory, no ``.pkl``, or any bad file (see :func:`load_recording`).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise RecordingError(f"{directory}: not a directory")
    files = sorted(directory.glob("*.pkl"), key=lambda p: (len(p.stem), p.stem))
    if not files:
        raise RecordingError(f"{directory}: no .pkl recordings found")
    recs = [load_recording(f, n_vertices, allow_gaps) for f in files]
    counts = {r.n_vertices for r in recs}
    if len(counts) > 1:
        raise RecordingError(f"{directory}: recordings have different marker counts {sorted(counts)}")
    return recs


def save_recording(path: str | Path, positions: np.ndarray) -> None:
    """Write positions in the DEFORM format (a list of (3, n) arrays).

    Args:
        path: the ``.pkl`` to write.
        positions: (T, n, 3) marker positions [m].
    """
    positions = np.asarray(positions, dtype=np.float64)
    frames = [np.ascontiguousarray(f.T) for f in positions]
    Path(path).write_bytes(pickle.dumps(frames, protocol=4))


def arclength_of(recordings) -> np.ndarray:
    """(n,) normalised arc-length position of each marker (median edge lengths over the data).

    Args:
        recordings: each ``positions`` (T, n, 3).

    Returns:
        (n,) in [0, 1].
    """
    edges = np.concatenate([np.linalg.norm(np.diff(r.positions[::25], axis=1), axis=-1) for r in recordings])
    s = np.concatenate([[0.0], np.cumsum(np.median(edges, axis=0))])
    return s / s[-1]
