"""A tracker for service tests that need no camera: the model alone, clouds ignored.

It has perception's ``Tracker`` interface (``initialize``, ``initialize_from_frames``, ``step``,
``correct`` -> ``(x, observed)``) and starts from perception's hanging-rope guess, settled briefly,
so estimator and predict tests run in a fraction of the real tracker's start-up."""

from __future__ import annotations

import numpy as np
import torch

from perception.initial import initial_guess


class OpenLoopTracker:
    def __init__(self, model, settle_steps: int = 300):
        self.model = model
        self.settle_steps = settle_steps
        self.state = None
        self.step_fn = None  # as perception's Tracker: None = model.step

    def _out(self):
        return self.state.x[0].numpy().copy(), np.zeros(self.model.n, dtype=bool)

    def initialize(self, grip, cloud=None, camera=None):
        grip = np.asarray(grip, dtype=float)
        rest = self.model.rest_lengths(torch.tensor(grip)).numpy().reshape(-1)
        x = initial_guess(grip, rest)
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

    def moment(self):
        """perception's Tracker's: what it was, to go back to (here the model state alone)."""
        return self.state

    def restore(self, moment):
        self.state = moment

    def correct(self, points_xyz, rgb, camera):
        return self._out()
