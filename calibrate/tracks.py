r"""Offline tracking of one clip: what the motion-capture recordings are to ``deform train``, these
tracks are to calibration.

The gripper poses are interpolated to the model's step :math:`\Delta t` (10 ms) at
:math:`t_k = t_0 + k \Delta t` (positions linearly, orientations by normalised linear interpolation
of the quaternions after aligning their signs: the poses come at 100 Hz or faster, where nlerp and
slerp differ by far less than a pose's noise), and turned into the gripped vertices by the service's
gripper convention (:func:`service.geometry.interpolate_poses`, :func:`service.geometry.grips_from_poses`). The track starts at the first cloud
(the tracker's model-free start, :meth:`perception.Tracker.initialize` with that cloud: a clip may
start in any state); the model steps every :math:`\Delta t`, and each cloud corrects the estimate
at the first step at or after its stamp, as the service does with a message clock: clouds are not
synchronous with the poses.

Besides the (T, n, 3) track, a :class:`Track` keeps which vertices each cloud corrected (the
tracker's ``observed``) and the cloud's rope points (:func:`calibrate.points.rope_points`), the
model-independent reference the fit is scored against.

Between clouds a track is the tracking model's own prediction and at each cloud it jumps to the
camera's correction: a sawtooth at the camera's rate. Training (:meth:`Track.recording`) therefore
scores its predictions only where and when a cloud corrected the track (:meth:`Track.at_clouds`),
against the corrected positions as they are, and starts its windows from the track smoothed in time
(:meth:`Track.smoothed`): started from the sawtooth, a window would read each jump as a velocity
(1 mm in one 10 ms step is 0.1 m/s). Scored against the smoothed track instead, training matched a
motion the filter had slowed, and the tracking model's own fill-in between clouds, and read both as
damping: on DLO2's clips filmed at 15 Hz (the calibration benchmark's other lab) the training loss
put the damping 1.25x above where the same loss on the motion-capture truth puts it, scored at the
clouds 0.99x (benchmarks/calibration_loss_bias.py).

For the start states each free vertex's coordinates are averaged twice over a window of exactly one
cloud interval :math:`T` (the median; :func:`moving_average`),

.. math:: \bar x(t) = \frac{1}{T} \int_{t - T/2}^{t + T/2} x(\tau)\, d\tau,

a triangle of base :math:`2T`. One window cancels what is periodic in :math:`T` (the sawtooth and its
harmonics) but, on the 10 ms grid with clouds 3 or 4 steps apart, leaves a fifth of each jump as a
step; the second leaves 7 % at 30 Hz and 1.5 % at 15 Hz. The rope's motion passes with gain
:math:`\operatorname{sinc}^2(f T)`: 0.97 at 3 Hz with 30 Hz clouds, 0.88 with 15 Hz. The Gaussian of
:math:`\sigma = T` used before removed the jumps better (1.3 % / 0.4 %) but passed 3 Hz with 0.82 /
0.45: on the DEFORM eval recordings it moved the true motion by 1.3 / 6.1 mm on average (the
triangle 0.3 / 1.3 mm), and calibration from 15 Hz clouds read the lost motion as damping. The
gripped vertices are inputs and kept.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from tqdm import tqdm

from calibrate.bags import Clip
from calibrate.points import rope_points
from deform import Recording, gripped_indices
from perception import Tracker
from service.config import Grippers
from service.geometry import grips_from_poses, interpolate_poses


@dataclass(frozen=True)
class Track:
    """A tracked clip. ``positions`` (T, n, 3) and ``grips`` (T, 4, 3) at ``dt``; ``cloud_steps``
    (C,) the step each cloud corrected; ``cloud_observed`` (C, n) the vertices it corrected (gripped
    ones are inputs: never); ``cloud_points`` C arrays (N_c, 3) of world rope points."""

    name: str
    positions: np.ndarray
    grips: np.ndarray
    dt: float
    cloud_steps: np.ndarray
    cloud_observed: np.ndarray
    cloud_points: tuple[np.ndarray, ...]
    status: dict

    @property
    def n_frames(self) -> int:
        return len(self.positions)

    @property
    def duration_s(self) -> float:
        return self.n_frames * self.dt

    @property
    def coverage(self) -> np.ndarray:
        """(n,) share of the clouds in which the camera corrected each vertex."""
        if len(self.cloud_observed) == 0:
            return np.zeros(self.positions.shape[1])
        return self.cloud_observed.mean(0)

    def recording(self) -> Recording:
        """The track as a :class:`deform.Recording` (what :func:`deform.train.train` takes): windows
        start from :meth:`smoothed`, predictions are scored against the track as corrected, weighted
        by :meth:`at_clouds`: training learns from what the camera showed, not from what the
        tracker's model filled in between clouds or behind an occluder."""
        return Recording(
            name=self.name,
            positions=self.smoothed(),
            dt=self.dt,
            weights=self.at_clouds(),
            targets=self.positions,
        )

    def smoothed(self) -> np.ndarray:
        """(T, n, 3) the free vertices averaged in time twice over one cloud interval (see the
        module); the gripped ones as tracked. A track with fewer than two clouds is returned as is."""
        if len(self.cloud_steps) < 2:
            return self.positions
        interval = float(np.median(np.diff(self.cloud_steps)))
        x = np.array(self.positions, dtype=np.float64, copy=True)
        free = np.setdiff1d(np.arange(x.shape[1]), gripped_indices(x.shape[1]))
        x[:, free] = moving_average(moving_average(x[:, free], interval), interval)
        return x

    def at_clouds(self) -> np.ndarray:
        """(T, n) 1 at the vertices a cloud corrected, at the step it corrected them, else 0 (the
        gripped vertices are inputs: 0)."""
        w = np.zeros(self.positions.shape[:2])
        w[self.cloud_steps] = self.cloud_observed
        w[:, gripped_indices(w.shape[1])] = 0.0
        return w


def moving_average(x: np.ndarray, width: float) -> np.ndarray:
    """``x`` (T, ...) sampled at unit steps, averaged along the first axis over a centred window of
    ``width`` steps (fractional: a 30 Hz camera's interval is 3.33 steps of 10 ms), the samples
    joined linearly; the ends are extended with the first and last values.

    Args:
        x: (T, ...) samples.
        width: the window [steps], > 0.

    Returns:
        (T, ...) the averages.
    """
    x = np.asarray(x, dtype=np.float64)
    n, half = len(x), 0.5 * width
    pad = int(np.ceil(half)) + 1
    xp = np.concatenate([np.repeat(x[:1], pad, 0), x, np.repeat(x[-1:], pad, 0)]).reshape(n + 2 * pad, -1)
    # the integral of the piecewise-linear signal at every sample, and within a step from sample i:
    # F(i + w) = F(i) + w x_i + w^2 (x_{i+1} - x_i) / 2
    F = np.concatenate([np.zeros((1, xp.shape[1])), np.cumsum(0.5 * (xp[1:] + xp[:-1]), axis=0)])

    def integral(q: np.ndarray) -> np.ndarray:
        i = np.minimum(np.floor(q).astype(int), len(xp) - 2)
        w = (q - i)[:, None]
        return F[i] + w * xp[i] + 0.5 * w * w * (xp[i + 1] - xp[i])

    t = np.arange(n, dtype=np.float64) + pad
    return ((integral(t + half) - integral(t - half)) / width).reshape(x.shape)


def track_clip(
    clip: Clip,
    model,
    grippers: Grippers,
    perception,
    rest: np.ndarray | None = None,
    progress: bool = False,
) -> Track | None:
    """Track one clip offline with ``model``.

    Args:
        clip: the bag's poses, clouds and camera.
        model: a :class:`deform.DeformModel` (its ``dt`` sets the track's step).
        grippers: the service config's gripper convention.
        perception: perception settings (:class:`perception.PerceptionConfig`).
        rest: (n-1,) rest lengths for the tracker's start (None: the model's).
        progress: a progress bar over the clip's steps.

    Returns:
        The :class:`Track`, or None when no cloud falls within the poses' time span.
    """
    dt = float(model.dt)
    step_ns = round(dt * 1e9)
    t_first, t_last = int(clip.pose_stamps_ns[0]), int(clip.pose_stamps_ns[-1])
    clouds = (c for c in clip.clouds() if t_first <= c[0] <= t_last)
    first = next(clouds, None)
    if first is None:
        return None
    t0 = first[0]
    times = np.arange(t0, t_last + 1, step_ns, dtype=np.int64)
    grips = grips_from_poses(interpolate_poses(clip.pose_stamps_ns, clip.poses, times), grippers)
    # the rope's length is the user's (checked against the camera by calibrate.checks): every clip
    # tracked at that one length, not at lengths the tracker took from the camera clip by clip; and
    # the track is the model's state, shapes the fitted rod can take (no camera residual on top); hidden
    # stretches stay the model's own (hidden_coherence: not yet measured on calibration, whose stored
    # results were tracked without it)
    model_state = replace(
        perception,
        tracker=replace(perception.tracker, length_gain=0.0, camera_residual=0.0, hidden_coherence=0.0),
    )
    tracker = Tracker(model, camera=clip.camera, config=model_state, rest=rest)
    seg = tracker.config.segmentation
    x, observed = tracker.initialize(grips[0], (first[1], first[2]), clip.camera)
    positions = [x]
    steps, seen, points = [0], [observed], [rope_points(first[1], first[2], clip.camera, seg)]
    pending = next(clouds, None)
    bar = tqdm(
        range(1, len(times)),
        desc=f"track {clip.name}",
        unit="step",
        leave=False,
        disable=None if progress else True,
    )
    for k in bar:
        x, observed = tracker.step(grips[k])
        while pending is not None and pending[0] <= times[k]:
            x, observed = tracker.correct(pending[1], pending[2], clip.camera)
            steps.append(k)
            seen.append(observed)
            points.append(rope_points(pending[1], pending[2], clip.camera, seg))
            pending = next(clouds, None)
        positions.append(x)
    return Track(
        name=clip.name,
        positions=np.asarray(positions),
        grips=grips,
        dt=dt,
        cloud_steps=np.asarray(steps),
        cloud_observed=np.asarray(seen, dtype=bool),
        cloud_points=tuple(points),
        status=tracker.status(),
    )


def cut(track: Track, start: int, stop: int, name: str | None = None) -> Track:
    """Steps ``start`` to ``stop`` of a track as a track of its own (a long recording split into
    clips, some held out).

    Args:
        track: the track.
        start: first step.
        stop: one past the last step.
        name: the new track's name (default ``<name>[start:stop]``).

    Returns:
        The :class:`Track`; its clouds are those whose steps fall inside.
    """
    keep = (track.cloud_steps >= start) & (track.cloud_steps < stop)
    return Track(
        name=name or f"{track.name}[{start}:{stop}]",
        positions=track.positions[start:stop],
        grips=track.grips[start:stop],
        dt=track.dt,
        cloud_steps=track.cloud_steps[keep] - start,
        cloud_observed=track.cloud_observed[keep],
        cloud_points=tuple(p for p, k in zip(track.cloud_points, keep) if k),
        status=track.status,
    )
