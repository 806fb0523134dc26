"""Synthetic gripper motions for the planted-effect generators' tests: no dataset needed."""

import math

import numpy as np

from deform.diagnose.spec import RodSpec
from deform.io.recordings import Recording

N, FRAMES, WINDOW = 10, 60, 40
SPEC = RodSpec(length_m=1.0, mass_kg=0.05, n_vertices=N, dt=0.01)


def swaying_source(phase: float) -> Recording:
    """A rope hanging in a half circle (radius 0.3 m, lowest point 0.2 m) between two grippers 0.6 m
    apart that sway sideways by 4 cm at 1 Hz, in opposite phase; 3 cm gripped end edges."""
    radius, edge = 0.3, 0.03
    arc = math.pi * radius
    s = np.concatenate([[0.0, edge], np.linspace(edge, arc - edge, N - 2)[1:-1], [arc - edge, arc]])
    theta = math.pi + s / radius
    base = np.stack([radius * np.cos(theta), np.zeros_like(theta), 0.5 + radius * np.sin(theta)], axis=1)
    t = np.arange(FRAMES) * SPEC.dt
    pos = np.repeat(base[None], FRAMES, axis=0)
    sway = 0.04 * np.sin(2 * math.pi * t + phase)
    pos[:, : N // 2, 1] += sway[:, None]
    pos[:, N // 2 :, 1] -= sway[:, None]
    return Recording(name=f"synthetic_{phase}", positions=pos, dt=SPEC.dt)
