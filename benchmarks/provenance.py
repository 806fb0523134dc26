"""What every stored benchmark result names: the command that wrote it, the commit and the machine.

    {**provenance(), ...}  ->  {"command": "python benchmarks/x.py ARGS", "commit": "abc1234",
                                "machine": {"host", "cpus", "cpu_model", "platform", "processor",
                                            "python", "torch", "torch_threads"}}

The command is this process's (``sys.argv``) in the form the docs give it, ``python
benchmarks/NAME.py ARGS``, whether the script was run so or as ``python -m benchmarks.NAME``. The
commit is the one checked out when this module was first imported (the run's start): a commit made
while a long run goes on is not the code it ran.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def source_commit() -> str:
    """Short hash of the checkout's HEAD ("" outside a git checkout)."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, timeout=30
        )
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return out.stdout.strip()


START_COMMIT = source_commit()  # at import: the run's start


def command_line(argv: list[str] | None = None, script: str | None = None) -> str:
    """``python benchmarks/NAME.py ARGS``: the script (``script``, else ``sys.argv[0]`` relative to
    the repository) and the arguments (``argv``, else ``sys.argv[1:]``)."""
    if script is None:
        path = Path(sys.argv[0]).resolve()
        try:
            script = str(path.relative_to(ROOT))
        except ValueError:
            script = sys.argv[0]
    args = sys.argv[1:] if argv is None else list(argv)
    return " ".join(["python", script, *args])


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU's model name ("" where the system does not say): two VMs of the same size and platform
    ran the same eager torch step 2.3x apart, so a stored time names the CPU it was taken on."""
    try:
        lines = cpuinfo.read_text().splitlines()
    except OSError:
        return ""
    for line in lines:
        key, _, value = line.partition(":")
        if key.strip() == "model name":
            return value.strip()
    return ""


def machine(threads: int | None = None, **extra) -> dict:
    """The machine a result was measured on; ``threads``: torch's intra-op threads of the measurement
    (default: this process's setting); ``extra``: more fields (e.g. ``native_bfloat16``)."""
    import torch

    return {
        "host": platform.node(),
        "cpus": os.cpu_count(),
        "cpu_model": cpu_model(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads() if threads is None else threads,
        **extra,
    }


def machine_text(m) -> str:
    """One line for a markdown table's caption (a stored machine is a dict, or a string in old files)."""
    if not isinstance(m, dict):
        return str(m)
    threads = m.get("torch_threads")
    return (
        f"{m.get('host', '?')}: {m.get('cpus', '?')} CPU cores"
        + (f" ({m['cpu_model']})" if m.get("cpu_model") else "")
        + f", {m.get('platform', '')}, "
        f"torch {m.get('torch', '')}"
        + (f" ({threads} thread{'s' if threads != 1 else ''})" if threads else "")
    )


def provenance(
    argv: list[str] | None = None, *, script: str | None = None, threads: int | None = None, **machine_extra
) -> dict:
    """``{"command", "commit", "machine"}`` of a stored result (see :func:`command_line`,
    :func:`machine`)."""
    return {
        "command": command_line(argv, script),
        "commit": START_COMMIT,
        "machine": machine(threads, **machine_extra),
    }
