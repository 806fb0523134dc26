"""Calibration clips as a lab would record them: a rod's training motions (never its held-out ones),
filmed by one camera placed once for the whole session, with noise, dropouts and, in every other
clip, an occluder in front of part of the rope; written as MCAP bags the way ``deform-service
record`` writes them, with the service config a user would write (the gripper convention).

Without the dataset, the motions are simulated with the rod's shipped model (the pipeline runs, the
numbers mean little).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml

from benchmarks.calibration.setups import Setup
from deform import Recording, find_data_root, generate_recording, load_model, load_recording, load_rod_config
from deform.io.arc_length import edge_lengths

DT = 0.01
CLIP_S = 5.0


@dataclass(frozen=True)
class Session:
    """What a calibration run is given: bags, the service config, the rope's length and mass."""

    bags: list[Path]
    config: Path
    length_m: float
    mass_kg: float
    seconds: float
    perception: Path | None = None  # the settings file the user passes (the rope's colour range)


def _sorted(files):
    return sorted(files, key=lambda p: (len(p.stem), p.stem))


def split_files(root: Path, rod: str) -> tuple[list[Path], list[Path]]:
    """``(train, held_out)`` files: ``train`` and ``eval``; without ``eval`` (DLO4, DLO5) the held-out
    fifth of ``train`` (every fifth by name, as training validates on it) and the rest."""
    train = _sorted((root / rod / "train").glob("*.pkl"))
    held = _sorted((root / rod / "eval").glob("*.pkl"))
    if not held:
        held = train[::5]
        train = [p for p in train if p not in held]
    return train, held


def motions(
    rod: str, seconds: float, root: Path | None = None, clip_set: int = 0
) -> tuple[list[Recording], list[Recording]]:
    """``(clips, held_out)``: enough training recordings for ``seconds`` of clips (spread over the
    training set, 5 s each; all of them when there are fewer), and the held-out recordings.

    ``clip_set`` k > 0 takes, for each clip of set 0, the k-th training recording after it (before
    it, for one near the end): another set of the same size and spread, disjoint from set 0 while 2k
    is below the spacing of its picks (6 recordings for 50 s of DLO1's 56), to see how much a
    calibration depends on which motions were filmed. The held-out recordings do not change.

    Without the dataset: simulated motions of the rod's shipped model, the held-out ones with other
    seeds (set k: the clips' seeds shifted by 1000 k)."""
    if clip_set < 0:
        raise ValueError(f"clip_set must be >= 0, got {clip_set}")
    want = max(round(seconds / CLIP_S), 1)
    root = root or find_data_root()
    if root is None:
        model = load_model(rod)
        shift = 1000 * clip_set
        clips = [
            generate_recording(model, 500, seed=2 * s + shift, name=f"sim{s + shift}") for s in range(want)
        ]
        held = [generate_recording(model, 500, seed=2 * s + 1, name=f"simheld{s}") for s in range(2)]
        return clips, held
    train, held = split_files(root, rod)
    pick = np.unique(np.linspace(0, len(train) - 1, min(want, len(train))).round().astype(int))
    shifted = pick + clip_set
    pick = np.unique(np.where(shifted < len(train), shifted, pick - clip_set))
    return [load_recording(train[i]) for i in pick], [load_recording(p) for p in held]


def write_session(rod: str, clips: list[Recording], out: Path, setup: Setup, camera) -> Session:
    """Render ``clips`` and write them as bags in ``out`` with the service config of their grippers
    and, when the lab's rope is not of the default colour, the settings file with its colour range.

    Args:
        rod: the rod (its length and mass are what the user gives).
        clips: the motions, each one clip.
        out: a directory (created).
        setup: how the lab films (benchmarks/calibration/setups.py).
        camera: the session's camera.
    """
    from perception import render_recording
    from service.bag import write_messages
    from service.scenario import build_stream, offsets_for

    out.mkdir(parents=True, exist_ok=True)
    render_cfg = setup.perception().render
    grippers = offsets_for(np.concatenate([c.positions for c in clips], axis=0))
    bags = []
    for i, clip in enumerate(clips):
        cfg = replace(render_cfg, occlusion=setup.occlusion_of_clip(i))
        frames = render_recording(
            clip.positions, dt=DT, fps=setup.fps, config=cfg, camera=camera, seed=1000 + i
        )
        bag = out / f"clip{i:03d}.mcap"
        write_messages(
            bag, "deform/rod1", build_stream(clip.positions, grippers, fps=setup.fps, seed=i, frames=frames)
        )
        bags.append(bag)
    config = out / "service.yaml"
    config.write_text(yaml.safe_dump({"grippers": grippers.model_dump()}))
    length, mass = held_length_and_mass(rod, clips)
    seconds = DT * sum(c.n_frames for c in clips)
    return Session(bags, config, length, mass, seconds, setup.settings_file(out))


def held_length_and_mass(rod: str, clips: list[Recording]) -> tuple[float, float]:
    """What a user gives ``--length`` and ``--mass``: the rope between the grippers, measured with a
    tape from grip point to grip point (the end markers: the median over the clips of the first
    frame's marker polyline), and its share of the weighed mass. The DEFORM ropes run on beyond the
    grippers: DLO1's 1.152 m spans 1.04 m between its end markers."""
    rod_cfg = load_rod_config(rod)  # the rope's length and mass, not the shipped model
    held = float(np.median([edge_lengths(c.positions[0]).sum() for c in clips]))
    held = min(held, rod_cfg.length_m)
    return round(held, 3), round(rod_cfg.mass_kg * held / rod_cfg.length_m, 5)
