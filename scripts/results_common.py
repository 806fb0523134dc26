"""Shared by the results page's renderers (scripts/make_results.py): number formatting, markdown
tables, nested look-ups and each file's provenance line. Standard library only."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def fmt(x, nd: int = 2, scale: float = 1.0) -> str:
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, float)):
        if isinstance(x, int) and scale == 1.0:
            return f"{x:,}".replace(",", " ")
        return f"{x * scale:.{nd}f}"
    return str(x)


def table(header: list[str], rows: list[list]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out + [""]


def get(d, *path, default=None):
    for p in path:
        if isinstance(d, dict) and p in d:
            d = d[p]
        else:
            return default
    return d


def git_last_commit(path: Path) -> str | None:
    """`<hash> (<date>)` of the last commit that changed ``path``, with a note when the working
    tree differs from it; None without git or when the file was never committed."""
    try:
        rel = str(path.resolve().relative_to(ROOT))
        log = subprocess.run(
            ["git", "log", "-1", "--format=%h (%cs)", "--", rel],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        if not log:
            return None
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", rel], cwd=ROOT, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        return log + ("; the working tree's copy differs from it" if dirty else "")
    except (OSError, ValueError, subprocess.SubprocessError):
        return None


def machine_text(m) -> str:
    if m is None:
        return "not recorded"
    if isinstance(m, dict):
        return ", ".join(f"{k} {v}" for k, v in m.items() if v not in ("", None))
    return str(m)


def render_generic(d) -> list[str]:
    if isinstance(d, list):
        return [
            f"A list of {len(d)} rows"
            + (f" with fields {', '.join(d[0])}." if d and isinstance(d[0], dict) else "."),
            "",
        ]
    if not isinstance(d, dict):
        return [f"Value: {d}", ""]
    rows = [
        [k, fmt(v, 4) if not isinstance(v, (dict, list)) else f"({type(v).__name__} of {len(v)})"]
        for k, v in d.items()
        if k not in ("command", "commit", "machine")
    ]
    return ["Top-level fields (this script has no table for this file):", ""] + table(
        ["field", "value"], rows
    )
