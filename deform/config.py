"""Rod configuration: what is known about a rod before any fitting (YAML in ``deform/rods/``, package
data, found through importlib.resources so an installed wheel has them too)."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

ROD_DIR = Path(str(files("deform") / "rods"))


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the file and the field."""


class RodConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str
    length_m: float = Field(gt=0)
    mass_kg: float = Field(gt=0)
    n_vertices: int = Field(ge=5)
    marker_mass_kg: float = Field(default=0.0004, ge=0)
    dt: float = Field(default=0.01, gt=0)
    # initial guesses of the material parameters (system identification refines them)
    bend_stiffness: float = Field(gt=0, description="EI [N m^2]")
    twist_stiffness: float = Field(gt=0, description="GJ [N m^2]")
    damping: float = Field(default=0.5, ge=0, description="linear velocity damping [1/s]")
    drag: float = Field(default=0.1, ge=0, description="quadratic air drag on the normal velocity [1/m]")
    stiffness_rank: int | None = None


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
