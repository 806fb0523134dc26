"""A restricted unpickler that admits only lists, numbers and numpy arrays.

`pickle.load` runs arbitrary code named in the stream; a recording is data, so we refuse every
global except the few numpy needs to rebuild an ndarray. Why by hand: no maintained library offers
an allow-list unpickler for numpy, and the standard library documents exactly this pattern.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
}


class UnsafePickleError(pickle.UnpicklingError):
    """The pickle names a global outside the allow-list (or is otherwise not plain data)."""


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) in _ALLOWED:
            return super().find_class(module, name)
        raise UnsafePickleError(f"refusing to load global {module}.{name}")

    def persistent_load(self, pid):
        raise UnsafePickleError("refusing persistent ids")


def safe_load_pickle(source: str | Path | bytes):
    """Load a pickle that may contain only lists, tuples, numbers and numpy arrays.

    Args:
        source: a path or the pickle's bytes.

    Returns:
        The unpickled lists, tuples, numbers and arrays.

    Raises:
        UnsafePickleError: the pickle names anything else (a class, a function: code it would run).
    """
    data = source if isinstance(source, bytes) else Path(source).read_bytes()
    try:
        return _RestrictedUnpickler(io.BytesIO(data)).load()
    except UnsafePickleError:
        raise
    except Exception as exc:  # truncated or garbage streams raise many different types
        raise UnsafePickleError(f"malformed pickle: {type(exc).__name__}: {exc}") from exc
