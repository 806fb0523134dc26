"""Shared fixtures: a synthetic recording (no dataset needed) and its rendered clouds, built once."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from deform import DeformModel, generate_recording, gripped_indices, load_rod_config
from perception import load_config, render_recording


@pytest.fixture(scope="session", autouse=True)
def one_thread():
    """The model's small tensors run fastest on one thread; restore the setting afterwards."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="session")
def model():
    """The configured (untrained) rod: tests do not change when the shipped models are retrained."""
    return DeformModel(load_rod_config("DLO2"))


@pytest.fixture(scope="session")
def recording(model):
    return generate_recording(model, n_frames=200, seed=2)  # seeds 1 and 3 go taut and unstable


@pytest.fixture(scope="session")
def grip_idx(model):
    return gripped_indices(model.n)


def occluded_config(fraction=0.3, start=0.0, end=1.0):
    cfg = load_config()
    return replace(
        cfg, render=replace(cfg.render, occlusion=fraction, occlusion_start=start, occlusion_end=end)
    )


@pytest.fixture(scope="session")
def occluded_frames(recording):
    """10 fps clouds of the synthetic recording, an occluder hiding ~30 % of the rope from 0.5 s on."""
    cfg = occluded_config(0.3, start=0.25, end=1.0)
    return render_recording(recording.positions, dt=recording.dt, fps=10, config=cfg, seed=1)


@pytest.fixture(scope="session")
def clear_frames(recording):
    """15 fps clouds of the synthetic recording, nothing hiding the rope."""
    return render_recording(recording.positions, dt=recording.dt, fps=15, seed=3)


def swung(x: np.ndarray, angle: float) -> np.ndarray:
    """The free vertices turned about the chord between vertices 1 and n-2 (a wrong initial shape)."""
    n = len(x)
    a, b = x[1], x[n - 2]
    k = (b - a) / np.linalg.norm(b - a)
    p = x - a
    rot = p * np.cos(angle) + np.cross(k, p) * np.sin(angle) + np.outer(p @ k, k) * (1 - np.cos(angle))
    out = x.copy()
    out[2 : n - 2] = (rot + a)[2 : n - 2]
    return out


def estimates(tracker, positions: np.ndarray, frames, grip_idx):
    """The service's loop on a recording: yields ``(k, estimate, corrected)`` at every step from 2 on,
    the model stepped with the recorded grippers and each of ``frames`` correcting it at its step."""
    by_step = {f.step: f for f in frames}
    for k in range(2, len(positions)):
        x, _ = tracker.step(positions[k, grip_idx])
        f = by_step.get(k)
        if f is not None:
            x, _ = tracker.correct(f.xyz, f.rgb, f.camera)
        yield k, x, f is not None
