"""DEFORM: differentiable discrete elastic rods for real-time estimation of ropes and cables.

Public API (perception, service and tools use only these names):

- :class:`DeformModel`, :class:`RodState`, :class:`ModelOptions`, :func:`load_model`,
  :func:`gripped_indices`: the model, its batched state and the trained models shipped per rod.
- :func:`load_recording`, :func:`load_recordings`, :func:`save_recording`, :class:`Recording`,
  :class:`RecordingError`, :func:`find_data_root`: safe reading of DEFORM recordings.
- :class:`RodConfig`, :func:`load_rod_config`, :class:`ConfigError`: rod configuration;
  :func:`generic_rod` and :func:`generic_model`: a rope known by its length and mass alone.
- :func:`generate_recording`: synthetic recordings from the simulator.
"""

from deform.config import (
    ConfigError,
    RodConfig,
    available_rods,
    bend_per_linear_density,
    generic_rod,
    load_rod_config,
)
from deform.io import (
    Recording,
    RecordingError,
    find_data_root,
    load_recording,
    load_recordings,
    save_recording,
)
from deform.model import (
    DeformModel,
    ModelOptions,
    RodState,
    generic_model,
    gripped_indices,
    load_model,
    overstretched,
)
from deform.synthetic import generate_recording

__all__ = [
    "ConfigError",
    "DeformModel",
    "ModelOptions",
    "Recording",
    "RecordingError",
    "RodConfig",
    "RodState",
    "available_rods",
    "bend_per_linear_density",
    "find_data_root",
    "generate_recording",
    "generic_model",
    "generic_rod",
    "gripped_indices",
    "load_model",
    "load_recording",
    "load_recordings",
    "load_rod_config",
    "overstretched",
    "save_recording",
]
