"""Benchmark of `deform diagnose` on datasets with one planted effect (and controls), then on the
real recordings DLO1..DLO5 against plain DER.

Planted data: deform.diagnose.planted (finer rod, smaller dt, markers a subset of nodes, 0.3 mm
noise, gripper motions replayed from real DLO2 recordings), or an independent simulator
(``--simulator elastica``: PyElastica, ``--simulator mujoco``: MuJoCo). The tool is not told the
effect. Writes benchmarks/results/diagnose.{json,md} (``--stem``: other names).

    python benchmarks/diagnose_planted.py [--quick | --smoke] [--seeds 3] [--control-seeds 5]
        [--effects a b ...] [--real DLO1 ...] [--fit 8 --check 4 --frames 500] [--summary-only]
        [--simulator own|elastica|mujoco] [--rod-kinds light stiff]
        [--num-cpus N] [--address ray://HOST:PORT | auto] [--inline]

Every dataset is a Ray task (benchmarks/cluster.py): on this machine a local Ray with one task per
core, or a cluster given by ``--address`` (or $RAY_ADDRESS). Each dataset's row is stored as soon as
it is done, one file per dataset in benchmarks/results/<stem>.runs/ (benchmarks/store.py); a rerun
with the same configuration skips the rows already there (resume after an interruption), and rows
of an older <stem>.runs.jsonl count too. The significance rule is reported twice: as the tool ran,
and calibrated on the controls (deform.diagnose.scoring.calibrate_min_gain) and re-applied to the
stored candidate scores. The code: the package benchmarks/planted/.
"""

import sys
from pathlib import Path

if not __package__:  # run as `python benchmarks/diagnose_planted.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.planted.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
