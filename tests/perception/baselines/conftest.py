"""Synthetic ropes for the peer trackers: points sampled evenly along a hanging curve, with noise."""

import numpy as np

GRIP = [0, 1, 11, 12]


def rope(n: int = 13, shift=(0.0, 0.0, 0.0), bend: float = 0.0, samples: int = 400):
    """(curve points (samples, 3), nodes (n, 3)): a 0.8 m span sagging 0.3 m, evenly sampled by arc length."""
    t = np.linspace(0, 1, 2000)
    c = np.stack([0.8 * t, 0.1 * np.sin(np.pi * t) * (1 + bend), -0.3 * np.sin(np.pi * t)], 1) + np.asarray(
        shift
    )
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))]

    def at(k):
        return np.stack([np.interp(np.linspace(0, s[-1], k), s, c[:, d]) for d in range(3)], 1)

    return at(samples), at(n)
