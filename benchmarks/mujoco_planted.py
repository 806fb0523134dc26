"""Recordings with one planted effect, made by a third rod simulator (MuJoCo): the detectability
table (per rod kind, a control, then each effect's marker L1 from it).

    python benchmarks/mujoco_planted.py [--sources 8] [--frames 300] [--kinds light stiff] [--effects ...]

The generator: benchmarks/planted/mujoco.py (its docstring tells the simulation).
"""

import sys
from pathlib import Path

if not __package__:  # run as `python benchmarks/mujoco_planted.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.planted.detectability import print_detectability_table
from benchmarks.planted.mujoco import EFFECTS, ROD_KINDS, generate_mujoco, grip_error

if __name__ == "__main__":
    print_detectability_table(
        generate_mujoco, grip_error, "Recordings with one planted effect, made by MuJoCo", ROD_KINDS, EFFECTS
    )
