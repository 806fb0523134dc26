"""The cores this process may run on: the default size of the pools of workers (the discrepancy
tool's fits, the calibration's clips). Not the service's: importing ``deform`` imports torch, which
``deform-service run`` defers until its workers have started.

``os.cpu_count()`` counts the machine's cores; a container or ``taskset`` may give the process fewer,
and more workers than those only take turns. The affinity mask says how many it has.
"""

from __future__ import annotations

import os


def available_cores() -> int:
    """The cores in this process's affinity mask (at least 1); the machine's count where the
    platform has no affinity (not Linux)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)
