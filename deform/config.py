"""Rod configuration: what is known about a rod before any fitting (YAML in ``deform/rods/``, package
data, found through importlib.resources so an installed wheel has them too)."""

from __future__ import annotations

import statistics
from importlib.resources import files
from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

ROD_DIR = Path(str(files("deform") / "rods"))

# A rod known only by its length L and mass m: bending stiffness EI = BEND_PER_LINEAR_DENSITY * m / L
# (heavier per metre means thicker, so stiffer), the median of EI L / m over the initial guesses of the
# five shipped rods (0.009-0.017 N m^3/kg); twisting stiffness GJ = TWIST_OVER_BEND * EI, their ratio.
# A starting point that system identification refines, not a measurement.
BEND_PER_LINEAR_DENSITY = 0.0124
TWIST_OVER_BEND = 0.7


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the file and the field."""


class RodConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str
    length_m: float = Field(gt=0)
    mass_kg: float = Field(gt=0)
    n_vertices: int = Field(default=12, ge=5)
    marker_mass_kg: float = Field(default=0.0004, ge=0)
    dt: float = Field(default=0.01, gt=0)
    # the bending forces stepped linearly implicitly (deform.rod.implicit): a stiff light cable's
    # bending modes are then stable at the 10 ms step. On for the shipped DLO2 and DLO3
    implicit_bending: bool = False
    # steps of dt / substeps per frame (grippers moved linearly between frames): for the stiffest
    # light cables, where even the implicit bending rings at one step a frame. 1 for the shipped models
    substeps: int = Field(default=1, ge=1, le=64)
    # initial guesses of the material parameters (system identification refines them); left out,
    # they follow from the length and mass (BEND_PER_LINEAR_DENSITY, TWIST_OVER_BEND)
    bend_stiffness: float = Field(default=None, gt=0, description="EI [N m^2]")
    twist_stiffness: float = Field(default=None, gt=0, description="GJ [N m^2]")
    damping: float = Field(default=0.5, ge=0, description="linear velocity damping [1/s]")
    drag: float = Field(default=0.1, ge=0, description="quadratic air drag on the normal velocity [1/m]")
    stiffness_rank: int | None = None

    @model_validator(mode="after")
    def _stiffness_from_length_and_mass(self) -> RodConfig:
        if self.bend_stiffness is None:
            self.bend_stiffness = BEND_PER_LINEAR_DENSITY * self.mass_kg / self.length_m
        if self.twist_stiffness is None:
            self.twist_stiffness = TWIST_OVER_BEND * self.bend_stiffness
        return self


def prior_rods(leave_out: tuple[str, ...] | list[str] = ()) -> list[str]:
    """The shipped rods the stiffness prior (:func:`bend_per_linear_density`) is the median over:
    every one not named in ``leave_out`` (a name not shipped here leaves nothing out)."""
    return [name for name in available_rods() if name not in set(leave_out)]


def bend_per_linear_density(leave_out: tuple[str, ...] | list[str] = ()) -> float:
    """The stiffness prior of a rod known by length and mass: the median of :math:`EI L / m` over the
    initial guesses of the shipped rods (``deform/rods/*.yaml``) not named in ``leave_out``. With
    none left out it is :data:`BEND_PER_LINEAR_DENSITY` (rounded); a benchmark that calibrates one
    of these rods leaves it out, so that the rod under test has no part in its own prior.

    Args:
        leave_out: rod names.

    Returns:
        The prior [N m^3/kg].

    Raises:
        ConfigError: every shipped rod left out.
    """
    values = []
    for name in prior_rods(leave_out):
        cfg = load_rod_config(name)
        values.append(cfg.bend_stiffness * cfg.length_m / cfg.mass_kg)
    if not values:
        raise ConfigError(f"no shipped rod is left for the stiffness prior once {sorted(leave_out)} are out")
    return float(statistics.median(values))


def generic_rod(
    length_m: float,
    mass_kg: float,
    n_vertices: int = 12,
    name: str = "generic",
    prior: float | None = None,
) -> RodConfig:
    """A rod known by its length and mass alone (no markers): what tracking a rope with no trained
    model, and camera-only calibration, start from.

    Args:
        length_m: length of the rope [m].
        mass_kg: its mass [kg].
        n_vertices: vertices of the discrete rod (including the four gripped ones).
        name: the rod's name.
        prior: bending stiffness per linear density [N m^3/kg] (None: :data:`BEND_PER_LINEAR_DENSITY`;
            see :func:`bend_per_linear_density`).

    Returns:
        The :class:`RodConfig`, stiffness from the prior and :data:`TWIST_OVER_BEND`.

    Raises:
        ConfigError: a non-positive length, mass or prior, or fewer than 5 vertices.
    """
    if prior is not None and not prior > 0:
        raise ConfigError(f"generic rod: a stiffness prior of {prior} (must be positive)")
    extra = {} if prior is None or not length_m > 0 else {"bend_stiffness": prior * mass_kg / length_m}
    try:
        return RodConfig(
            name=name, length_m=length_m, mass_kg=mass_kg, n_vertices=n_vertices, marker_mass_kg=0.0, **extra
        )
    except ValidationError as exc:
        raise ConfigError(f"generic rod: {str(exc).replace(chr(10), '; ')}") from None


def available_rods() -> list[str]:
    return sorted(p.stem for p in ROD_DIR.glob("*.yaml"))


def load_rod_config(name_or_path: str | Path) -> RodConfig:
    """Load ``deform/rods/<name>.yaml`` (a shipped rod) or a YAML path.

    Args:
        name_or_path: a shipped rod's name or a YAML file.

    Returns:
        The :class:`RodConfig`.

    Raises:
        ConfigError: an unknown rod, a missing file or a bad field, named.
    """
    path = Path(name_or_path)
    if not path.suffix:
        path = ROD_DIR / f"{name_or_path}.yaml"
        if not path.is_file():
            raise ConfigError(f"unknown rod {str(name_or_path)!r}; known rods: {', '.join(available_rods())}")
    if not path.is_file():
        raise ConfigError(f"{path}: no such file")
    try:
        data = yaml.safe_load(path.read_text())
        return RodConfig(**data)
    except (yaml.YAMLError, TypeError, ValidationError) as exc:
        msg = str(exc).replace("\n", "; ")
        raise ConfigError(f"{path}: {msg}") from None
