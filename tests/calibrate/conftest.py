"""Tiny synthetic clips: a plain DER (1 m, 50 g) moved by random gripper motions, rendered by
perception's renderer into the message stream a robot and a camera send, written as MCAP."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from deform import generate_recording, generic_model
from service.bag import write_messages
from service.scenario import build_stream, offsets_for

LENGTH, MASS, N = 1.0, 0.05, 12
FRAMES, FPS = 150, 10.0  # 1.5 s clips, a cloud every 10 steps


@dataclass
class Clips:
    dir: Path
    bags: list[Path]  # three moving clips
    truths: list[np.ndarray]  # (T, n, 3) each
    messages: list  # the first clip's message stream
    config: Path  # service config with the gripper convention the clips were made with
    grippers: object


def _write(path, messages):
    write_messages(path, "deform/rod1", messages)
    return path


@pytest.fixture(scope="session")
def clips(tmp_path_factory) -> Clips:
    d = tmp_path_factory.mktemp("clips")
    model = generic_model(LENGTH, MASS, N)
    bags, truths, first = [], [], None
    grippers = None
    for seed in range(3):
        rec = generate_recording(model, n_frames=FRAMES, seed=seed)
        grippers = offsets_for(rec.positions)
        msgs = build_stream(rec.positions, grippers, fps=FPS, seed=seed)
        first = first or msgs
        bags.append(_write(d / f"clip{seed}.mcap", msgs))
        truths.append(rec.positions)
    config = d / "service.yaml"
    config.write_text(yaml.safe_dump({"grippers": grippers.model_dump()}))
    return Clips(d, bags, truths, first, config, grippers)


@pytest.fixture(scope="session")
def still_bag(clips) -> Path:
    """A rope held still for 2.5 s: nothing to identify."""
    rec = generate_recording(generic_model(LENGTH, MASS, N), n_frames=2, seed=0)
    positions = np.repeat(rec.positions[:1], 250, axis=0)
    return _write(clips.dir / "still.mcap", build_stream(positions, clips.grippers, fps=FPS, seed=0))
