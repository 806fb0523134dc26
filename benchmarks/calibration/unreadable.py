"""A calibration that cannot read the calibrated rope's shipped files, as the acceptance runs it.

Issue 49's acceptance calibrates a DEFORM rope "with that rope's shipped model files removed". Deleting
them from the checkout would leave them deleted when a run is killed, so the calibration runs instead in
processes that cannot open them: a ``sitecustomize`` module on ``PYTHONPATH`` installs a Python audit
hook (PEP 578) that refuses every ``open`` of those paths. Python imports ``sitecustomize`` at start-up,
so the hook is in the calibration's process and in every process it spawns (its workers inherit the
environment). A calibration that read one of the files fails; it cannot quietly use it.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ENV = "DEFORM_UNREADABLE"  # the refused files, os.pathsep-separated ends of their paths

HOOK = f'''"""Refuses to open the files named in ${ENV} (benchmarks/calibration/unreadable.py)."""
import os
import sys

_REFUSED = tuple(os.sep + p for p in os.environ.get("{ENV}", "").split(os.pathsep) if p)


def _refuse_open(event, args):
    if event == "open" and _REFUSED and isinstance(args[0], (str, bytes, os.PathLike)):
        path = os.path.realpath(os.fsdecode(args[0]))
        if path.endswith(_REFUSED):
            raise PermissionError(f"{{path}}: withheld from this process (the rope's shipped files)")


sys.addaudithook(_refuse_open)
'''


def shipped_files(rod: str) -> list[str]:
    """What a shipped rod comes with, as the ends of their paths (refused in any checkout or install
    of the package, whichever one the subprocess imports): its trained model and its rod config with
    the marker layout and initial parameter guesses."""
    return [f"deform/models/{rod}.pt", f"deform/rods/{rod}.yaml"]


@contextmanager
def withheld(path_ends: list[str]) -> Iterator[dict[str, str]]:
    """The environment of a subprocess that cannot open a file whose path ends in one of
    ``path_ends`` (nor can any process it starts).

    Yields:
        ``os.environ`` with the hook's directory first on ``PYTHONPATH`` and the path ends in
        ``$DEFORM_UNREADABLE``.
    """
    if any(not e or e.startswith("/") or os.pathsep in e for e in path_ends):
        raise ValueError(f"path ends must be relative and non-empty: {path_ends}")
    hook_dir = Path(tempfile.mkdtemp(prefix="withheld_"))
    try:
        (hook_dir / "sitecustomize.py").write_text(HOOK)
        python_path = os.pathsep.join(p for p in (str(hook_dir), os.environ.get("PYTHONPATH", "")) if p)
        yield dict(os.environ, PYTHONPATH=python_path, **{ENV: os.pathsep.join(path_ends)})
    finally:
        shutil.rmtree(hook_dir, ignore_errors=True)
