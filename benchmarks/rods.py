"""The rods of the planted-effect benchmarks and the recorded motions that drive them: one table,
read by the benchmark (:mod:`benchmarks.planted`) and by the simulators' own command lines
(the detectability tables ``benchmarks/elastica_planted.py``, ``benchmarks/mujoco_planted.py``).

* ``RODS``: the DEFORM rods, name -> (length [m], mass [kg], markers);
* ``SOURCE_ROD``: the rod kind an independent simulator plants effects on -> the real rod whose
  length, mass and recorded gripper motions it takes (light: DLO1, stiff: DLO3, medium: DLO2);
* ``OWN_SOURCE_ROD``: the real rod whose motions drive this project's own planted data (DLO2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deform.diagnose.spec import RodSpec
from deform.io.recordings import find_data_root, load_recordings

RODS = {
    "DLO1": (1.152, 0.0345, 13),
    "DLO2": (0.996, 0.0652, 12),
    "DLO3": (0.998, 0.0968, 12),
    "DLO4": (0.973, 0.022, 12),
    "DLO5": (0.988, 0.0192, 12),
}
# real gripper motions driving each rod kind; medium is a held-out third rod, run only when asked
# (--rod-kinds medium), so that the stored commands of the light and stiff benchmarks keep their meaning
SOURCE_ROD = {"light": "DLO1", "stiff": "DLO3", "medium": "DLO2"}
DEFAULT_ROD_KINDS = ("light", "stiff")
OWN_SOURCE_ROD = "DLO2"


def data_root(root: Path | None = None) -> Path:
    """The DEFORM recordings (``root``, else ``$DEFORM_DATA`` or ``../shared/data/deform``)."""
    root = root or find_data_root()
    if root is None:
        raise SystemExit("no dataset: set DEFORM_DATA")
    return root


def rod_spec(rod: str, name: str | None = None, dt: float | None = None) -> RodSpec:
    """The RodSpec of the DEFORM rod ``rod`` (``name`` and ``dt`` when given)."""
    L, M, n = RODS[rod]
    extra = {} if dt is None else {"dt": dt}
    return RodSpec(length_m=L, mass_kg=M, n_vertices=n, name=name or rod, **extra)


def independent_rod(kind: str, root: Path | None = None, simulator: str = "elastica") -> tuple[RodSpec, list]:
    """The independent-simulator benchmark's rod of ``kind`` (light, stiff, medium): its spec as a user
    gives it and the recorded train motions of its source rod that drive it."""
    rod = SOURCE_ROD[kind]
    return rod_spec(rod, f"{kind}-{simulator}"), load_recordings(data_root(root) / rod / "train")


def seeded_sources(sources: list, seed: int, count: int) -> list:
    """``count`` source recordings picked by ``seed`` (with repeats only when there are fewer)."""
    pick = np.random.default_rng(seed).choice(len(sources), count, replace=len(sources) < count)
    return [sources[i] for i in pick]


def own_rod() -> RodSpec:
    """The rod this project's own simulator plants effects on (DLO2's length, mass and markers)."""
    return rod_spec(OWN_SOURCE_ROD, f"{OWN_SOURCE_ROD}-planted")


def own_sources(root: Path | None = None) -> list:
    """The recorded train motions that drive the own simulator's planted data."""
    return load_recordings(data_root(root) / OWN_SOURCE_ROD / "train")


def own_pick(sources: list, seed: int, count: int) -> list:
    """``count`` different source recordings picked by ``seed`` (the own planted datasets)."""
    pick = np.random.default_rng(seed).choice(len(sources), count, replace=False)
    return [sources[i] for i in pick]


def own_dataset_sources(seed: int, count: int) -> tuple[list, RodSpec]:
    """The sources and rod of the own simulator's dataset of ``seed``."""
    return own_pick(own_sources(), seed, count), own_rod()
