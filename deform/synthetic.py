"""Recordings made by the project's own simulator, so everything runs without the real dataset.

A rod of the configured length hangs between two grippers that start a little closer than the rod
is long, settles under gravity, then the grippers follow smooth random motions (sums of a few
sinusoids, amplitudes and speeds like those of the real recordings).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from deform.config import RodConfig
from deform.io.recordings import Recording
from deform.model import gripped_indices


def _rotation_z(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    r = np.zeros(angle.shape + (3, 3))
    r[..., 0, 0], r[..., 0, 1], r[..., 1, 0], r[..., 1, 1], r[..., 2, 2] = c, -s, s, c, 1.0
    return r


def straight_rod(cfg: RodConfig, height: float = 0.5) -> np.ndarray:
    """(n, 3): a straight rod along +x, centred at the origin, at ``height``.

    Args:
        cfg: the rod (its length and vertex count).
        height: z of the rod [m].

    Returns:
        (n, 3) vertices [m].
    """
    n = cfg.n_vertices
    x = np.zeros((n, 3))
    x[:, 0] = np.linspace(-cfg.length_m / 2, cfg.length_m / 2, n)
    x[:, 2] = height
    return x


def smooth_motion(rng: np.random.Generator, t: np.ndarray, amplitude: float, n_modes: int = 3) -> np.ndarray:
    """(T, 3) smooth displacement starting at zero, a few random sinusoids per axis.

    Args:
        rng: the random generator.
        t: (T,) times [s].
        amplitude: largest displacement per axis, about [m].
        n_modes: sinusoids per axis.

    Returns:
        (T, 3) displacements [m].
    """
    out = np.zeros((len(t), 3))
    for axis in range(3):
        for _ in range(n_modes):
            freq = rng.uniform(0.1, 0.6)
            phase = rng.uniform(0, 2 * math.pi)
            amp = amplitude * rng.uniform(0.3, 1.0) / n_modes
            out[:, axis] += amp * (np.sin(2 * math.pi * freq * t + phase) - math.sin(phase))
    return out


def gripper_trajectory(
    cfg: RodConfig, x_rest: np.ndarray, n_frames: int, seed: int, amplitude: float = 0.2, sag: float = 0.25
) -> np.ndarray:
    """(T, 4, 3) positions of vertices 0, 1, n-2, n-1: the two ends pulled ``sag``·L closer, then moving.

    Args:
        cfg: the rod.
        x_rest: (n, 3) the straight rod the grippers start from.
        n_frames: frames.
        seed: the motion.
        amplitude: size of the motion [m].
        sag: how much closer the ends are pulled, as a fraction of the length.

    Returns:
        (n_frames, 4, 3) gripped vertices [m].
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) * cfg.dt
    n = cfg.n_vertices
    ends = x_rest[gripped_indices(n)]
    out = np.empty((n_frames, 4, 3))
    for side, sign in ((0, 1.0), (1, -1.0)):
        pair = ends[2 * side : 2 * side + 2]
        anchor = pair[0] if side == 0 else pair[1]
        local = pair - anchor
        # the first 0.8 s pull the ends together; afterwards a smooth random motion and a yaw wobble
        ramp = np.clip(t / 0.8, 0, 1)
        ramp = ramp * ramp * (3 - 2 * ramp)
        pull = np.zeros((n_frames, 3))
        pull[:, 0] = sign * 0.5 * sag * cfg.length_m * ramp
        wiggle = smooth_motion(rng, t, amplitude) * np.clip((t - 1.0) / 0.5, 0, 1)[:, None]
        yaw = 0.3 * np.sin(2 * math.pi * rng.uniform(0.1, 0.4) * t) * np.clip((t - 1.0) / 0.5, 0, 1)
        rotated = np.einsum("tij,kj->tki", _rotation_z(sign * yaw), local)
        out[:, 2 * side : 2 * side + 2] = anchor + pull[:, None] + wiggle[:, None] + rotated
    free_length = np.linalg.norm(np.diff(x_rest, axis=0), axis=1)[1:-1].sum()
    return _keep_slack(out, free_length * (1 - sag / 2))


def _keep_slack(grips: np.ndarray, max_span: float) -> np.ndarray:
    """Pull both ends towards their midpoint where the inner gripped vertices would be further
    apart than ``max_span`` (after the first frame), so that the rod is never stretched taut."""
    inner = grips[:, 2] - grips[:, 1]
    span = np.linalg.norm(inner, axis=-1)
    excess = np.clip(span - max_span, 0, None)
    excess[0] = 0.0
    shift = (excess / np.maximum(span, 1e-9) / 2)[:, None] * inner
    out = grips.copy()
    out[:, :2] += shift[:, None]
    out[:, 2:] -= shift[:, None]
    return out


def generate_recording(
    model,
    n_frames: int = 500,
    seed: int = 0,
    amplitude: float = 0.2,
    warmup_s: float = 2.5,
    noise_m: float = 0.0,
    name: str | None = None,
) -> Recording:
    """Simulate ``model`` under random smooth gripper motion: a recording without a camera.

    The first ``warmup_s`` seconds (ends pulled together, rod settling) are dropped.

    Args:
        model: a :class:`deform.model.DeformModel` (its physics make the motion).
        n_frames: frames kept, at the model's ``dt``.
        seed: gripper motion and initial bow.
        amplitude: size of the gripper motion [m].
        warmup_s: settling time dropped from the start [s].
        noise_m: standard deviation of Gaussian marker noise added [m].
        name: the recording's name (default from the seed).

    Returns:
        A :class:`deform.io.Recording` with ``positions`` (n_frames, n, 3).
    """
    cfg = model.cfg
    warm = round(warmup_s / cfg.dt)
    x_rest = straight_rod(cfg)
    grips = gripper_trajectory(cfg, x_rest, n_frames + warm + 1, seed, amplitude)
    rng = np.random.default_rng(seed + 10_000)
    # a tiny random initial bow so that the rod does not start on an unstable straight line
    x0 = x_rest.copy()
    x0[2:-2, 2] -= 1e-3 * np.sin(np.linspace(0, math.pi, cfg.n_vertices))[2:-2]
    x0[2:-2] += rng.normal(0, 1e-5, x0[2:-2].shape)
    dtype = torch.float64
    state = model.static_state(
        torch.tensor(x0, dtype=dtype),
        rest=torch.tensor(np.linalg.norm(np.diff(x_rest, axis=0), axis=1)[None], dtype=dtype),
    )
    frames = []
    g = torch.tensor(grips, dtype=dtype)
    with torch.no_grad():
        for k in range(1, n_frames + warm + 1):
            state = model.step(state, g[k].unsqueeze(0))
            if k > warm:
                frames.append(state.x[0].numpy().copy())
    positions = np.stack(frames)
    if noise_m > 0:
        positions = positions + rng.normal(0, noise_m, positions.shape)
    return Recording(name=name or f"synthetic_{seed}", positions=positions, dt=cfg.dt)
