"""The service's view of perception: a tracker factory, the camera built from ROS messages, and an
open-loop tracker (model only) used when perception is not installed, so the service still runs.

Everything here goes through perception's public names only (``Tracker``, ``Camera``).
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from service.geometry import pose_matrix

log = logging.getLogger("deform.service")


def _perception(name: str):
    """``perception.<name>`` or None while perception does not provide it yet."""
    try:
        import perception

        return getattr(perception, name, None)
    except ImportError:
        return None


def make_camera(K: np.ndarray, width: int, height: int, pose: np.ndarray):
    """A perception Camera from CameraInfo's K and the camera pose (x y z qx qy qz qw, optical frame)."""
    Camera = _perception("Camera")
    if Camera is None:
        from perception.camera import Camera  # until perception exports it at the top level
    return Camera(
        float(K[0, 0]),
        float(K[1, 1]),
        float(K[0, 2]),
        float(K[1, 2]),
        int(width),
        int(height),
        pose_matrix(np.asarray(pose, dtype=float)),
    )


def hanging_guess(grip: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A rod hanging in a vertical parabola between vertices 1 and n-2 with the given rest lengths
    (n-1,) (the model's nominal ones). -> positions (n, 3) and rest lengths (n-1,)."""
    n = len(rest) + 1
    inner = max(float(np.sum(rest[1:-1])), 1.05 * np.linalg.norm(grip[2] - grip[1]))
    s = np.linspace(0.0, 1.0, n - 2)
    chord = grip[1][None] + s[:, None] * (grip[2] - grip[1])[None]
    lo, hi = 0.0, inner
    for _ in range(50):  # bisection on the sag so the polyline has the inner length
        sag = 0.5 * (lo + hi)
        pts = chord.copy()
        pts[:, 2] -= 4 * sag * s * (1 - s)
        if np.linalg.norm(np.diff(pts, axis=0), axis=1).sum() < inner:
            lo = sag
        else:
            hi = sag
    x = np.concatenate([grip[:1], pts, grip[3:]])
    return x, np.asarray(rest, dtype=np.float64)


class OpenLoopTracker:
    """The model alone: the estimate follows the grippers, clouds are ignored (observed = False).
    Same interface as perception's Tracker."""

    def __init__(self, model, settle_steps: int = 300):
        self.model = model
        self.settle_steps = settle_steps
        self.state = None
        self.step_fn = None  # as perception's Tracker: None = model.step

    def _out(self):
        return self.state.x[0].numpy().copy(), np.zeros(self.model.n, dtype=bool)

    def initialize(self, grip, cloud=None, camera=None):
        grip = np.asarray(grip, dtype=float)
        x, rest = hanging_guess(grip, self.model.rest_lengths(grip).numpy())
        with torch.no_grad():
            state = self.model.static_state(torch.tensor(x)[None], rest=torch.tensor(rest)[None])
            self.state = self.model.settle(
                state, torch.tensor(grip)[None], max_steps=self.settle_steps, tol=1e-3
            )
        return self._out()

    def initialize_from_frames(self, x0, x1):
        with torch.no_grad():
            self.state = self.model.initial_state(
                torch.as_tensor(x0, dtype=torch.float64)[None], torch.as_tensor(x1, dtype=torch.float64)[None]
            )
        return self._out()

    def step(self, grip_next):
        with torch.no_grad():
            self.state = (self.step_fn or self.model.step)(
                self.state, torch.as_tensor(np.asarray(grip_next), dtype=torch.float64)[None]
            )
        return self._out()

    def correct(self, points_xyz, rgb, camera):
        return self._out()


def make_tracker(model, **kwargs):
    """perception's Tracker when installed, else the open-loop tracker (logged once)."""
    Tracker = _perception("Tracker")
    if Tracker is None:
        log.warning("perception.Tracker not available: running open-loop (clouds are counted, not fused)")
        return OpenLoopTracker(model)
    return Tracker(model, **kwargs)


def rod_state(tracker, model, x_prev: np.ndarray | None, x: np.ndarray):
    """The full model state behind the tracker's estimate (for prediction): the tracker's own when it
    exposes one, else rebuilt from the last two estimates."""
    state = getattr(tracker, "state", None)
    if state is not None and hasattr(state, "rest"):
        return state
    x_prev = x if x_prev is None else x_prev
    return model.initial_state(torch.tensor(x_prev)[None], torch.tensor(x)[None])
