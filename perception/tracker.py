"""The tracker: the DEFORM model predicts at the model rate, camera clouds correct it when they come.

Errors in the loop are contained here: bad gripper inputs, failed model steps and unusable clouds
leave the tracker running open-loop with vertices marked unobserved; nothing raises and no NaN is
returned from :meth:`Tracker.step` or :meth:`Tracker.correct`.

A correction can only repair errors within ``filter_radius``. Beyond that (the rope was hidden and
the model drifted, a motion too fast for it, a model of another rope) every cloud is checked
(:mod:`perception.recovery`): when most visible rope points are unexplained, or the rope was not
seen for ``lost_after_s``, the tracker counts the rope as lost and finds it again from the cloud
alone, anchored at the grippers, then goes on tracking from there (:attr:`Tracker.health`).

Two shapes are kept: the model's state, always on its rest lengths (it is what the model steps and
predicts from), and the estimate :attr:`Tracker.x`, which at the vertices the last cloud observed
also keeps part of what the projection onto the rest lengths took back from the camera
(``camera_residual``, across the rope only).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields, replace

import numpy as np
import torch

from deform import gripped_indices
from perception.camera import Camera
from perception.cloud import decimate, depth_image, depth_noise, voxel_downsample
from perception.config import load_config
from perception.estimate import coherent_shift, correct_vertices, occluded_vertices
from perception.initial import initial_guess
from perception.length import seen_length
from perception.recovery import TrackingHealth, disagreement, explained_cost, rope_from_points
from perception.segment import segment_rope

log = logging.getLogger(__name__)

NOISE_DEPTH_BAND = 0.1  # m: the depth noise is measured this far in front of and behind the rope


@dataclass(frozen=True)
class TrackerMoment:
    """What a tracker was after one model step, to go back to (:meth:`Tracker.moment`,
    :meth:`Tracker.restore`): a cloud that arrives late is fused at the step it was taken and the
    steps since are replayed. Health counters and the camera's length of the rope are not part of it
    (what the camera taught since is kept)."""

    state: object  # deform.RodState
    grip: np.ndarray | None
    observed: np.ndarray
    since_update: float
    residual: np.ndarray


class Tracker:
    """Rod state estimate for one rod. ``physics=False`` gives the non-physical baseline (free
    vertices stay where last seen, only the gripped ones follow the grippers).

    ``step_fn``: what advances the model, called like ``model.step(state, grip)``; default the
    model's own step (e.g. a :class:`deform.compiled.CompiledStep` in a real-time loop)."""

    def __init__(
        self,
        model,
        camera: Camera | None = None,
        config=None,
        physics: bool = True,
        rest: np.ndarray | None = None,
        gmm_backend: str = "numpy",
        step_fn=None,
    ):
        self.model = model
        self.step_fn = step_fn
        self.n = int(model.n)
        self.dt = float(model.dt)
        self.camera = camera
        self.config = load_config(config)
        self.physics = physics
        self.rest = None if rest is None else np.asarray(rest, dtype=np.float64)
        self.gmm_backend = gmm_backend
        self.grip_idx = gripped_indices(self.n)
        self.movable = np.ones(self.n, dtype=bool)
        self.movable[self.grip_idx] = False
        self.state = None
        self._observed = np.zeros(self.n, dtype=bool)
        self._since_update = np.inf
        self._grip = None
        self.health = TrackingHealth()
        self._length_ratio = 1.0  # running camera length / rest length of the free rope
        self._rest_start = None  # the free rest lengths before the camera's length replaced them
        self._residual = np.zeros((self.n, 3))  # camera over model at the observed vertices (see x)
        self._hidden_fill = np.zeros((self.n, 3))  # the last correction's shift of hidden vertices

    # ----- public API -----------------------------------------------------------------------
    @property
    def x(self) -> np.ndarray:
        """The estimate (n, 3) [m]: the model's state, plus at the vertices the last cloud observed
        (while it is fresh, ``stale_after_s``) ``camera_residual`` of what the projection onto the
        rest lengths took back from the correction. The state itself stays on its rest lengths (the
        model steps from it); where the model cannot take the shape the camera shows (another rope's
        rest lengths, a contact it does not know), the estimate keeps that share of the camera's."""
        x = self._model_x()
        if self._since_update * self.dt <= self.config.tracker.stale_after_s:
            x += self._residual
        return x

    @property
    def observed(self) -> np.ndarray:
        if self._since_update * self.dt > self.config.tracker.stale_after_s:
            return np.zeros(self.n, dtype=bool)
        return self._observed.copy()

    def status(self) -> dict:
        """Loss and recovery (see :class:`perception.recovery.TrackingHealth`): ``state``
        (tracking or lost), ``lost`` / ``recovered`` / ``redetected`` counts, ``since_seen_s`` and
        the last cloud's ``disagreement``."""
        return self.health.as_dict(self.dt)

    def moment(self) -> TrackerMoment | None:
        """The tracker now, to :meth:`restore` later (None before it is initialised). Copies: a
        few small tensors and arrays."""
        if self.state is None:
            return None
        state = replace(
            self.state, **{f.name: getattr(self.state, f.name).clone() for f in fields(self.state)}
        )
        grip = None if self._grip is None else self._grip.copy()
        return TrackerMoment(state, grip, self._observed.copy(), self._since_update, self._residual.copy())

    def restore(self, moment: TrackerMoment) -> None:
        """Back to ``moment`` (from :meth:`moment` of this tracker or a copy of it)."""
        self.state = moment.state
        self._grip = None if moment.grip is None else moment.grip.copy()
        self._observed = moment.observed.copy()
        self._since_update = moment.since_update
        self._residual = moment.residual.copy()

    def hold_still(self) -> None:
        """The rope at rest where it is (its velocity zero): after its grippers jumped in one step (a
        pose sender that paused while the robot moved), the step's projection moved the free rope
        that far in one period, and that velocity would throw it on."""
        if self.state is not None:
            self.state = replace(self.state, v=torch.zeros_like(self.state.v))

    def initialize_from_frames(self, x0: np.ndarray, x1: np.ndarray):
        """State at ``x1`` from two consecutive full observations (the paper's protocol).

        Args:
            x0: (n, 3) vertices one step before ``x1`` [m].
            x1: (n, 3) vertices now [m].

        Returns:
            ``(x, observed)``: x (n, 3) the estimate, observed (n,) bool, all False.
        """
        x0 = torch.as_tensor(np.asarray(x0, dtype=np.float64)).unsqueeze(0)
        x1 = torch.as_tensor(np.asarray(x1, dtype=np.float64)).unsqueeze(0)
        with torch.no_grad():
            self.state = self.model.initial_state(x0, x1)
        self.rest = self.state.rest[0].numpy().copy()
        self._forget_camera()
        self._grip = x1[0, self.grip_idx].numpy().copy()
        self._mark(np.ones(self.n, dtype=bool))
        return self.x, self.observed

    def initialize(self, grip: np.ndarray, cloud=None, camera: Camera | None = None):
        """State from the grippers and optionally a first cloud: a guess aligned with the visible
        rope, settled by the model with the grippers fixed, then corrected by the same cloud.

        Args:
            grip: (4, 3) vertices 0, 1, n-2, n-1 held by the grippers [m], world frame.
            cloud: camera-frame ``xyz`` ((H, W, 3) or (N, 3)) or ``(xyz, rgb)``, or None.
            camera: the cloud's camera (default: the tracker's).

        Returns:
            ``(x, observed)``: x (n, 3) world-frame vertices, observed (n,) bool.
        """
        grip = np.asarray(grip, dtype=np.float64).reshape(4, 3)
        if self.rest is None:
            # the marker spacing the model learnt from recordings; the end edges as the grippers hold them
            self.rest = self.model.rest_lengths(grip).numpy()
        camera = camera or self.camera
        xyz, rgb = cloud if isinstance(cloud, (tuple, list)) else (cloud, None)
        pts = None
        if xyz is not None and camera is not None:
            pts = camera.to_world(segment_rope(xyz, rgb, self.config.segmentation))
        x = initial_guess(grip, self.rest, pts)
        if pts is not None and len(pts):
            found = rope_from_points(pts, grip, self.rest)
            cap = self.config.estimation.filter_radius
            if found is not None and explained_cost(pts, found, cap) < explained_cost(pts, x, cap):
                x = found
            depth = depth_image(xyz, camera)
            for _ in range(self.config.tracker.init_em_rounds):
                x, _ = correct_vertices(
                    x, pts, depth, camera, self.config.estimation, self.movable, self.gmm_backend
                )
        tx = torch.as_tensor(x).unsqueeze(0)
        rest = torch.as_tensor(self.rest).unsqueeze(0)
        g = torch.as_tensor(grip).unsqueeze(0)
        tc = self.config.tracker
        with torch.no_grad():
            state = self.model.static_state(tx, rest=rest)
            if self.physics:
                state = self.model.settle(state, g, max_steps=tc.settle_max_steps, tol=tc.settle_tol)
        self.state = replace(state, v=torch.zeros_like(state.x))
        self._forget_camera()
        self._grip = grip
        self._observed[:] = False
        self._since_update = np.inf  # no velocity nudge from the corrections below
        if xyz is not None and camera is not None:
            return self.correct(xyz, rgb, camera)
        return self.x, self.observed

    def step(self, grip_next: np.ndarray):
        """Predict one model step (``model.dt``).

        Args:
            grip_next: (4, 3) gripped vertices at the new time [m], world frame.

        Returns:
            ``(x, observed)``: x (n, 3), observed (n,) bool (camera updates younger than
            ``stale_after_s``). Never raises: a bad input keeps the last estimate.
        """
        grip = self._valid_grip(grip_next)
        if grip is None:
            log.warning("no valid gripper input yet; nothing to predict")
            return np.zeros((self.n, 3)), np.zeros(self.n, dtype=bool)
        if self.state is None:
            return self.initialize(grip)
        self._since_update += 1
        self.health.since_seen_steps += 1
        if self.physics:
            try:
                with torch.no_grad():
                    new = (self.step_fn or self.model.step)(self.state, torch.as_tensor(grip).unsqueeze(0))
                if bool(torch.isfinite(new.x).all()) and bool(torch.isfinite(new.v).all()):
                    self.state = new
                    self._grip = grip
                    return self.x, self.observed
                log.warning("model step gave non-finite values; holding the shape")
            except Exception as exc:  # the loop must go on
                log.warning("model step failed (%s); holding the shape", exc)
        self._hold(grip)
        return self.x, self.observed

    def correct(self, points_xyz: np.ndarray, rgb: np.ndarray | None = None, camera: Camera | None = None):
        """Correct the estimate's observed vertices from a cloud (occlusion-aware: filtered by the
        prediction, depth-checked, DBSCAN groups, a GMM per group).

        Args:
            points_xyz: camera-frame points (H, W, 3) organised or (N, 3) [m], NaN where missing.
            rgb: uint8 colours of the same leading shape, or None (depth-only segmentation).
            camera: the cloud's camera (default: the tracker's).

        Returns:
            ``(x, observed)``: x (n, 3) world-frame vertices, observed (n,) bool. Never raises: a
            bad cloud leaves the estimate open-loop.
        """
        if self.state is None:
            log.warning("correct() before initialize(); ignored")
            return np.full((self.n, 3), 0.0), np.zeros(self.n, dtype=bool)
        camera = camera or self.camera
        try:
            if camera is None or points_xyz is None:
                raise ValueError("no camera or no cloud")
            xyz = np.asarray(points_xyz)
            if xyz.ndim < 2 or xyz.shape[-1] != 3:
                raise ValueError(f"cloud of shape {xyz.shape}")
            colours = None if rgb is None else np.asarray(rgb)
            small, colours = decimate(xyz, colours, self.config.estimation.max_points)
            pts = camera.to_world(segment_rope(small, colours, self.config.segmentation))
            depth = depth_image(xyz, camera)
            seen = voxel_downsample(pts, self.config.estimation.voxel)
            x_pred = self._find_if_lost(pts, seen)
            est = self._estimation(depth, x_pred, camera)
            self._hidden_fill = np.zeros((self.n, 3))
            x_new, observed = self._corrected(x_pred, pts, depth, camera, est)
            found = self._camera_over_model(pts, seen, x_new)
            if found is not None:
                x_new, observed = self._corrected(found, pts, depth, camera, est)
            if not np.all(np.isfinite(x_new)):
                raise ValueError("non-finite correction")
            self._follow_length(seen, x_new)
        except Exception as exc:
            log.warning("camera update skipped: %s", exc)
            self._observed[:] = False
            return self.x, self.observed
        x_t = torch.as_tensor(x_new, dtype=self.state.x.dtype).unsqueeze(0)
        v_t = self.state.v
        gain = self.config.tracker.velocity_gain
        if gain > 0 and self.physics and np.isfinite(self._since_update) and self._since_update > 0:
            # the hidden vertices' fill is a guess, not a measurement: it moves them, not their velocity
            # (nudged by it, hidden stretches swung: 50 % occluded 3.1 -> 3.8 mm, tracking_peers)
            moved = x_t - self.state.x - torch.as_tensor(self._hidden_fill, dtype=x_t.dtype).unsqueeze(0)
            v_t = v_t + gain * moved / (self._since_update * self.dt)
        self.state = self.model.reposition(self.state, x_t, v_t)
        self._mark(observed)
        self._residual = self._across_rope(x_new, observed)
        return self.x, self.observed

    # ----- internals --------------------------------------------------------------------------
    def _estimation(self, depth: np.ndarray, x_pred: np.ndarray, camera: Camera):
        """The estimation settings for this cloud: the occlusion margin at least ``occlusion_noise``
        times the depth noise the cloud shows within ``NOISE_DEPTH_BAND`` of the rope's depths. A
        noisy camera (8 mm at 1.6 m) otherwise hides visible vertices behind their own rope's
        noisiest pixels."""
        cfg = self.config.estimation
        if cfg.occlusion_noise <= 0:
            return cfg
        _, z = camera.project(camera.to_camera(x_pred))
        sigma = depth_noise(depth, float(z.min()) - NOISE_DEPTH_BAND, float(z.max()) + NOISE_DEPTH_BAND)
        self.health.depth_noise_mm = 1e3 * sigma if sigma > 0 else None
        margin = cfg.occlusion_noise * sigma
        return replace(cfg, occlusion_margin=margin) if margin > cfg.occlusion_margin else cfg

    def _corrected(self, x_pred: np.ndarray, pts: np.ndarray, depth: np.ndarray, camera: Camera, cfg):
        """The camera's correction of ``x_pred`` (:func:`perception.estimate.correct_vertices`); at
        the visible free vertices it left alone, ``coherence`` of their corrected neighbours' shift,
        and at the hidden ones ``hidden_coherence`` of the shift of their nearest corrected (or so
        filled) neighbours on each side (``cfg``: the estimation settings for this cloud,
        :meth:`_estimation`)."""
        x_new, observed = correct_vertices(x_pred, pts, depth, camera, cfg, self.movable, self.gmm_backend)
        share, hidden_share = self.config.tracker.coherence, self.config.tracker.hidden_coherence
        if not observed.any() or (share <= 0 and hidden_share <= 0):
            return x_new, observed
        visible = self.movable & ~occluded_vertices(x_pred, depth, camera, cfg)
        if share > 0:
            x_new = x_new + share * coherent_shift(x_new - x_pred, observed, visible)
        if hidden_share > 0:
            known = observed | visible if share > 0 else observed
            hidden = self.movable & ~visible & ~observed
            self._hidden_fill = hidden_share * coherent_shift(x_new - x_pred, known, hidden)
            x_new = x_new + self._hidden_fill
        return x_new, observed

    def _forget_camera(self) -> None:
        """A new start: nothing the camera told the last track (its length, its residual) carries over."""
        self._length_ratio, self._rest_start = 1.0, None
        self._residual[:] = 0.0

    def _across_rope(self, x_new: np.ndarray, observed: np.ndarray) -> np.ndarray:
        """``camera_residual`` of what the projection took back from the correction ``x_new``, at the
        observed free vertices, across the rope only: the camera shows where a featureless rope lies
        across, not how far along it a vertex sits (that component the state's projection keeps)."""
        x = self._model_x()
        r = x_new - x
        tangent = np.gradient(x, axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        r -= np.sum(r * tangent, axis=1, keepdims=True) * tangent
        kept = observed & self.movable
        if kept.any():
            self.health.camera_over_model_mm = 1e3 * float(np.linalg.norm(r[kept], axis=1).mean())
        return np.where(kept[:, None], r, 0.0) * self.config.tracker.camera_residual

    def _model_x(self) -> np.ndarray:
        """The model state's vertices (n, 3): what the model predicts and steps from."""
        return self.state.x[0].numpy().astype(np.float64).copy()

    def _follow_length(self, seen: np.ndarray, x_new: np.ndarray) -> None:
        """The camera's length of the free rope over the rest length (:mod:`perception.length`),
        averaged over the clouds that show it whole; when it strays beyond ``length_trigger`` the
        free rest lengths take it (a model of another rope, a length given wrong), within
        ``length_bounds`` of where they started. The projection in the coming ``reposition``
        then keeps the camera's length instead of bending the rope into a sag the cloud never showed."""
        tc = self.config.tracker
        if tc.length_gain <= 0 or not self.physics or len(seen) < tc.min_seen_points:
            return
        length = seen_length(seen, x_new, self.config.estimation.assoc_radius)
        if length is None:
            return
        rest = self.state.rest[0].double().numpy().copy()
        self._length_ratio += tc.length_gain * (length / rest[1:-1].sum() - self._length_ratio)
        if abs(self._length_ratio - 1.0) <= tc.length_trigger:
            return
        if self._rest_start is None:
            self._rest_start = rest[1:-1].copy()
        lo, hi = tc.length_bounds
        rest[1:-1] = np.clip(rest[1:-1] * self._length_ratio, lo * self._rest_start, hi * self._rest_start)
        self.state = replace(self.state, rest=torch.as_tensor(rest, dtype=self.state.rest.dtype).unsqueeze(0))
        self.rest = rest
        self._length_ratio = 1.0
        self.health.length_scale = float(rest[1:-1].sum() / self._rest_start.sum())

    def _explains(self, seen: np.ndarray, found: np.ndarray, better_than: float) -> bool:
        """Does a shape from the cloud alone explain the rope points below ``better_than`` and as
        well as a tracked rope does (``refind_cost``)? The second keeps a blob of rope-coloured
        clutter, through which a path can always be drawn, from becoming the rope."""
        cost = explained_cost(seen, found, self.config.estimation.filter_radius)
        limit = self.config.tracker.refind_cost
        return cost < better_than and (limit <= 0 or cost <= limit)

    def _camera_over_model(self, pts: np.ndarray, seen: np.ndarray, x_new: np.ndarray) -> np.ndarray | None:
        """A shape from the cloud alone when the corrected estimate still does not explain the
        visible rope (capped mean point distance above ``refind_cost``: the model carried it where
        one correction cannot bring it back, e.g. through a table it does not know of) and that
        shape explains the points clearly better, with points near ``refind_seen`` of its free
        vertices. The state is moved there at rest: the model's velocity was what took it away.
        ``seen`` is ``pts`` voxel-downsampled. None: keep the correction."""
        tc, radius = self.config.tracker, self.config.estimation.filter_radius
        if len(seen) < tc.min_seen_points or tc.refind_cost <= 0:
            return None
        cost = explained_cost(seen, x_new, radius)
        if cost <= tc.refind_cost:
            return None
        grip = self._grip if self._grip is not None else x_new[self.grip_idx]
        found = rope_from_points(pts, grip, self.rest)
        if found is None or not self._explains(seen, found, tc.redetect_gain * cost):
            return None
        # only a rope seen nearly whole: where the cloud shows gaps, the shape bridges them straight
        near = np.linalg.norm(found[2:-2, None] - seen[None], axis=-1).min(1)
        if np.mean(near < self.config.estimation.assoc_radius) < tc.refind_seen:
            return None
        x_t = torch.as_tensor(found, dtype=self.state.x.dtype).unsqueeze(0)
        self.state = self.model.reposition(self.state, x_t, torch.zeros_like(x_t))
        self._since_update = np.inf
        self.health.redetected += 1
        return self._model_x()

    def _find_if_lost(self, pts: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """The prediction to correct: the model's, or a shape found from the cloud alone when the
        rope was lost and that shape explains the points clearly better (then the state is moved
        there, at rest, and no velocity nudge follows). ``seen`` is ``pts`` voxel-downsampled."""
        tc, radius = self.config.tracker, self.config.estimation.filter_radius
        x_pred = self._model_x()
        if len(seen) < tc.min_seen_points:
            if self.health.since_seen_steps * self.dt > tc.lost_after_s:
                self.health.lose()
            return x_pred
        self.health.since_seen_steps = 0
        share = disagreement(seen, x_pred, radius)
        self.health.disagreement = share
        if share <= tc.lost_fraction:
            self.health.recover(redetected=False)  # back, or never gone: the camera agrees
            return x_pred
        self.health.lose()
        grip = self._grip if self._grip is not None else x_pred[self.grip_idx]
        found = rope_from_points(pts, grip, self.rest)
        if found is None or not self._explains(
            seen, found, tc.redetect_gain * explained_cost(seen, x_pred, radius)
        ):
            return x_pred
        x_t = torch.as_tensor(found, dtype=self.state.x.dtype).unsqueeze(0)
        self.state = self.model.reposition(self.state, x_t, torch.zeros_like(x_t))
        self._since_update = np.inf
        self.health.recover(redetected=True)
        return self._model_x()

    def _mark(self, observed: np.ndarray) -> None:
        self._observed = observed & self.movable
        self._since_update = 0

    def _valid_grip(self, grip_next) -> np.ndarray | None:
        try:
            grip = np.asarray(grip_next, dtype=np.float64).reshape(4, 3)
            if np.all(np.isfinite(grip)):
                return grip
        except Exception:
            pass
        log.warning("invalid gripper input; keeping the last one")
        return self._grip

    def _hold(self, grip: np.ndarray) -> None:
        """Non-physical prediction: free vertices stay, gripped ones follow the grippers."""
        x = self.state.x.clone()
        x[0, self.grip_idx] = torch.as_tensor(grip, dtype=x.dtype)
        self.state = replace(self.state, x=x, v=torch.zeros_like(x))
        self._grip = grip
