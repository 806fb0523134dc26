"""The foreign lab (:mod:`benchmarks.calibration.foreign_lab`) in the calibration benchmark: its clips
written as that lab's bags, and the held-out motions filmed by it and read back through `deform
calibrate`'s own bag reader, the path a lab's recordings take (its topics, frames, intrinsics and
missing points reach the tracker only as they reach the service).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from benchmarks.calibration.clips import DT, Session, held_length_and_mass
from benchmarks.calibration.foreign_lab import ForeignLab, place_camera, write_clip, write_session
from deform import Recording

FOREIGN = "foreign"
# the foreign lab as it films, and with a driver that stamps its clouds on arrival, 50 ms late
FOREIGN_LABS = {FOREIGN: ForeignLab(), "foreign_late": ForeignLab(stamp_delay_s=0.05)}


def foreign_camera(lab: ForeignLab, positions: list[np.ndarray]) -> np.ndarray:
    """The foreign lab's one camera for the session (4x4 world from optical frame)."""
    return place_camera(np.concatenate(positions, axis=0), lab)


def foreign_perception(lab: ForeignLab):
    """Perception's defaults with the foreign lab's colour range: what its user passes."""
    from perception import load_config

    p = load_config(None)
    return replace(p, segmentation=replace(p.segmentation, hsv_low=lab.hsv_low, hsv_high=lab.hsv_high))


def write_foreign_session(
    rod: str, clips: list[Recording], out: Path, lab: ForeignLab, world_from_optical: np.ndarray
) -> Session:
    """The clips as the foreign lab's bags, its service config and its colour range file."""
    bags, config, colour = write_session(out, [c.positions for c in clips], DT, lab, world_from_optical)
    length, mass = held_length_and_mass(rod, clips)
    seconds = DT * sum(c.n_frames for c in clips)
    return Session(list(bags), config, length, mass, seconds, colour)


def film_foreign(
    recording: Recording,
    i: int,
    lab: ForeignLab,
    world_from_optical: np.ndarray,
    work: Path,
    config: Path,
    stamp_delay_s: float = 0.0,
) -> list:
    """The clouds of held-out motion ``i`` as the foreign lab records them (an occluder throughout
    its middle half), read back with :func:`calibrate.bags.read_clip`: frames at the first model step
    at or after each cloud's stamp less ``stamp_delay_s``, as a message-clock service configured with
    ``camera.stamp_delay_s`` fuses them."""
    from calibrate.bags import read_clip
    from service.config import load_config

    path = work / f"held{i:02d}"
    write_clip(path, recording.positions, DT, lab, world_from_optical, seed=2000 + i, occluded=True)
    clip = replace(read_clip(path, load_config(config)), cloud_delay_ns=round(stamp_delay_s * 1e9))
    t0 = int(clip.pose_stamps_ns[0])  # the first pose is the motion's first frame
    frames = []
    for stamp, xyz, rgb in clip.clouds():
        step = math.ceil((stamp - t0) / (DT * 1e9) - 1e-6)
        if 2 <= step < recording.n_frames:
            frames.append(SimpleNamespace(step=step, xyz=xyz, rgb=rgb, camera=clip.camera))
    return frames
