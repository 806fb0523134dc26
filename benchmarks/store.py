"""One result file per dataset: what a benchmark run stores as each of its datasets finishes, so that
a stopped run resumes by skipping the datasets already stored.

A benchmark's rows live in a directory (``benchmarks/results/<stem>.runs/``), one subdirectory per
configuration (the settings a row depends on: a row is reused only by a run with the same ones),
one JSON file per dataset key::

    diagnose.elastica.runs/check=4-fit=8-frames=500-quick=False-tool=12/elastica.light.none.0.json

Files are written atomically (a temporary file renamed over the target), by the process that runs
the benchmark only (Ray tasks return their rows to it). Rows stored before this layout, appended to
one ``<stem>.runs.jsonl`` file, are read as well (never written).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import tempfile
from pathlib import Path


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=+,-]", ".", text)


def _value(v) -> str:
    if isinstance(v, (list, tuple)):
        return ",".join(map(_value, v))
    return json.dumps(v, sort_keys=True, separators=(",", ":")).replace('"', "")


def config_name(config: dict) -> str:
    """The directory name of a configuration: its fields, sorted, ``key=value`` joined by ``-``
    (a long one shortened, with a hash of the whole)."""
    name = _slug("-".join(f"{k}={_value(v)}" for k, v in sorted(config.items())))
    if len(name) > 150:
        digest = hashlib.sha1(json.dumps(config, sort_keys=True).encode()).hexdigest()[:10]
        name = f"{name[:120]}-{digest}"
    return name


def source_digest(*packages: str, root: Path | None = None) -> str:
    """A short hash of the Python sources of ``packages`` (folders or files under ``root``, by
    default the checkout): put in a configuration, it keeps rows computed by older code from being
    reused."""
    root = root or Path(__file__).resolve().parents[1]
    h = hashlib.sha1()
    for package in packages:
        where = root / package
        for path in [where] if where.is_file() else sorted(where.rglob("*.py")):
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:10]


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that a reader sees the old file or the new one, never a part."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_result(
    stem: Path, result: dict, failures, what: str, markdown: str | None = None, indent: int = 1
) -> int:
    """A run's end: ``<stem>.json`` (and ``<stem>.md`` when given), the tasks that failed named on
    stderr. -> the exit code (1 when any failed: their rows are not stored, a rerun does them)."""
    write_atomic(stem.with_name(stem.name + ".json"), json.dumps(result, indent=indent) + "\n")
    if markdown is not None:
        write_atomic(stem.with_name(stem.name + ".md"), markdown)
    if failures:
        print(f"{len(failures)} {what} failed, not stored: {', '.join(failures)}", file=sys.stderr)
        return 1
    return 0


class RunStore:
    """The stored rows of one benchmark (``directory``; ``legacy``: an old append-only runs file).

    A row is a dict with at least ``"key"`` (the dataset) and ``"config"``."""

    def __init__(self, directory: Path, legacy: Path | None = None):
        self.directory = Path(directory)
        self.legacy = legacy
        self._old: list[dict] | None = None  # the old runs file's rows, read once

    @classmethod
    def for_runs(cls, runs: str | Path) -> RunStore:
        """The store of ``X.runs`` (a directory), reading old rows of ``X.runs.jsonl`` beside it; either
        name may be given."""
        runs = Path(runs)
        directory = runs.with_suffix("") if runs.suffix == ".jsonl" else runs
        return cls(directory, directory.with_name(directory.name + ".jsonl"))

    def path(self, key: str, config: dict) -> Path:
        return self.directory / config_name(config) / f"{_slug(key.replace(':', '.'))}.json"

    def has(self, key: str, config: dict) -> bool:
        return self.path(key, config).is_file() or key in self._legacy(config)

    def load(self, config: dict) -> dict[str, dict]:
        """Every stored row of ``config``, by key (a row file takes precedence over an old runs file's)."""
        rows = self._legacy(config)
        folder = self.directory / config_name(config)
        if folder.is_dir():
            for path in sorted(folder.glob("*.json")):
                row = json.loads(path.read_text())
                if row.get("config") == config:
                    rows[row["key"]] = row
        return rows

    def save(self, row: dict) -> Path:
        """Store ``row`` (atomically); -> its file."""
        path = self.path(row["key"], row["config"])
        write_atomic(path, json.dumps(row) + "\n")
        return path

    def where(self, config: dict) -> str:
        """Where the rows of ``config`` are stored (for a table's caption): the directory, and the old
        runs file when it holds some."""
        old = [self.legacy.name] if self.legacy is not None and self._legacy(config) else []
        return " and ".join([*old, f"{self.directory.name}/"])

    def _legacy(self, config: dict) -> dict[str, dict]:
        if self._old is None:
            self._old = []
            if self.legacy is not None and self.legacy.is_file():
                lines = self.legacy.read_text().splitlines()
                self._old = [json.loads(line) for line in lines if line.strip()]
        return {row["key"]: row for row in self._old if row.get("config") == config}
