"""Recordings with one planted effect, made by an independent rod simulator (PyElastica): the
detectability table (per rod kind, a control, then each effect's marker L1 from it).

    python benchmarks/elastica_planted.py [--sources 8] [--frames 300] [--kinds light stiff] [--effects ...]

The generator: benchmarks/planted/elastica.py (its docstring tells the simulation).
"""

import sys
from pathlib import Path

if not __package__:  # run as `python benchmarks/elastica_planted.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.planted.detectability import print_detectability_table
from benchmarks.planted.elastica import EFFECTS, ROD_KINDS, element_strain, generate_elastica

if __name__ == "__main__":
    print_detectability_table(
        generate_elastica,
        element_strain,
        "Recordings with one planted effect, made by PyElastica",
        ROD_KINDS,
        EFFECTS,
    )
