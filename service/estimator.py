"""The estimation core, free of any transport: validated inputs in, one estimate per tick out.

Thread model: input handlers may be called from any thread and only swap small "latest" values; the
tracker is advanced by :meth:`Estimator.tick` (the loop thread) and by cloud fusion (see
``service.fusion``) under one lock that is never held for a whole cloud fusion.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from service import messages as M
from service.config import ServiceConfig
from service.geometry import grips_from_poses, pose_matrix
from service.pose_timeline import RESET_S, PoseGrid, PoseTimeline
from service.stats import Stats
from service.tracking import camera_frame_cloud, cloud_intrinsics, make_camera, make_tracker, organize_cloud

NS = 1_000_000_000


@dataclass
class Estimate:
    stamp_ns: int  # the time the state describes: that of the gripper poses it stepped to
    x: np.ndarray  # (n, 3) float64, world
    observed: np.ndarray  # (n,) bool
    grip: np.ndarray  # (4, 3) the gripped vertices used
    poses: np.ndarray  # (2, 7) the gripper poses used
    tick: int


@dataclass
class Cloud:
    """A decoded, subsampled cloud ready for the tracker."""

    stamp_ns: int
    xyz: np.ndarray  # (H, W, 3) float32, camera frame, NaN = no return
    rgb: np.ndarray  # (H, W, 3) uint8
    camera: object  # perception Camera (intrinsics + world_from_camera)


class Tick(NamedTuple):
    """One loop tick as cloud fusion needs it: the grip it stepped to, the stamp of the poses that
    gave it and, when clouds are fused at their stamps, the tracker after it (its ``moment()``)."""

    index: int
    grip: np.ndarray
    pose_ns: int
    moment: object | None  # None when clouds are fused where they arrive


class Estimator:
    def __init__(
        self,
        cfg: ServiceConfig,
        model,
        tracker=None,
        stats: Stats | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.cfg, self.model = cfg, model
        self.clock = clock  # wall time (s) for arrivals, ages and the cloud rate limit; tests pass a fake
        self.wall_ns = time.time_ns  # the clock message stamps are on (a cloud's age when fused)
        self.tracker = tracker if tracker is not None else make_tracker(model, config=cfg.perception)
        self.stats = stats or Stats(cfg.namespace)
        self.lock = threading.RLock()
        self.message_clock = cfg.clock == "message"
        self.stale_ns = int(cfg.timeouts.stale_s * NS)
        self.cloud_delay_ns = round(cfg.camera.stamp_delay_s * NS)
        # latest inputs
        self.poses: tuple[int, np.ndarray, np.ndarray] | None = None  # stamp, (2,7) poses, (4,3) grip
        # wall clock: the poses sampled one period a tick by their stamps (None: the newest as it is)
        steady = not self.message_clock and cfg.pose_delay_s != 0
        self.timeline = PoseTimeline(cfg.dt, cfg.pose_delay_s) if steady else None
        # message clock: ticks every dt of the poses' own time (not one per message)
        self.grid = PoseGrid(cfg.dt) if self.message_clock else None
        # message clock: the grid's ticks not yet taken, (time, poses, the grid started again there)
        self.grid_ticks: deque[tuple[int, np.ndarray, bool]] = deque()
        self.newest_ns: int | None = None
        self.camera_info: tuple[np.ndarray, int, int] | None = None
        self.fitted_intrinsics: dict[tuple[int, int], np.ndarray] = {}  # (w, h) -> K of the clouds' own
        self.camera_pose = np.asarray(cfg.camera.pose, dtype=float)
        self.last_cloud_ns: int | None = None
        self.last_cloud_arrival = self.clock()
        self.cloud_tokens = 3.0
        self.pending: list[Cloud] = []  # message clock: clouds waiting for their tick
        self.arrived: dict[str, float] = {}  # input -> arrival (wall monotonic or message time, s)
        self.fused_at: float | None = None
        # estimate
        self.initialized = False
        self.tick_index = 0
        self.history: deque[Tick] = deque(maxlen=512)  # so fusion can go back to a cloud's tick and catch up
        # wall clock: a cloud is fused at the tick of its stamp (needs a tracker that can go back)
        self.rewinds = (
            not self.message_clock and cfg.camera.fuse_at == "stamp" and hasattr(self.tracker, "moment")
        )
        self.estimate: Estimate | None = None
        self.prev_x: np.ndarray | None = None
        self.clock_s = 0.0  # message time of the last tick (message clock)
        self.last_cloud: Cloud | None = None  # the last fused cloud (for logging)
        self.step_fn = None  # the compiled step once ready (see use_step); None: the model's own

    def use_step(self, step_fn) -> None:
        """Advance the tracker with ``step_fn`` from the next tick on (trackers swapped in by cloud
        fusion get it too)."""
        with self.lock:
            self.step_fn = step_fn
            if hasattr(self.tracker, "step_fn"):
                self.tracker.step_fn = step_fn

    # ----- time --------------------------------------------------------------------------------
    def now(self) -> float:
        return self.clock_s if self.message_clock else self.clock()

    def _arrive(self, key: str, stamp_ns: int) -> None:
        self.arrived[key] = stamp_ns / NS if self.message_clock else self.clock()

    def _check_stamp(self, topic: str, stamp: int, last: int | None) -> None:
        if last is not None and stamp <= last:
            raise M.InputError("out_of_order", f"stamp {stamp} <= {last}")
        # message clock: compare with the time already estimated (arrival order across keys is not
        # guaranteed, so the newest stamp seen would make the outcome depend on transport timing)
        ref = int(self.clock_s * NS) if self.message_clock else self.newest_ns
        if ref and stamp < ref - self.stale_ns:
            raise M.InputError("stale", f"{(ref - stamp) / NS:.3f} s old")

    def _see(self, stamp: int) -> None:
        self.newest_ns = stamp if self.newest_ns is None else max(self.newest_ns, stamp)

    # ----- inputs ------------------------------------------------------------------------------
    def parse_poses(self, raw: bytes, last: int | None):
        """-> (stamp, poses (2, 7), grip (4, 3)) or None (counted and logged)."""
        try:
            stamp, poses = M.parse_pose_array(raw, frame_id=self.cfg.frame_id)
            self._check_stamp("ee_poses", stamp, last)
            return stamp, poses, grips_from_poses(poses, self.cfg.grippers)
        except M.InputError as exc:
            self.stats.reject("ee_poses", exc.reason, str(exc))
            return None

    def set_poses(self, parsed) -> list[int]:
        """Take a parsed pose message; on the message clock, the times of the ticks it completes
        (:class:`service.pose_timeline.PoseGrid`; the wall clock's timer ticks: empty)."""
        with self.lock:
            self.poses = parsed
            if self.timeline is not None:
                self.timeline.add(parsed[0], parsed[1])
            due = self.grid.add(parsed[0], parsed[1]) if self.grid is not None else []
            # a grid started again after a gap: the grippers jump to its first tick's poses
            self.grid_ticks.extend((t, p, i == 0 and self.grid.restarted) for i, (t, p) in enumerate(due))
            self._see(parsed[0])
            self._arrive("ee_poses", parsed[0])
            return [t for t, _ in due]

    def on_poses(self, raw: bytes) -> bool:
        parsed = self.parse_poses(raw, self.poses[0] if self.poses else None)
        if parsed is not None:
            self.set_poses(parsed)
        return parsed is not None

    def on_camera_info(self, raw: bytes) -> bool:
        try:
            stamp, K, w, h = M.parse_camera_info(raw)
        except M.InputError as exc:
            self.stats.reject("camera_info", exc.reason, str(exc))
            return False
        self.camera_info = (K, w, h)
        self._arrive("camera_info", stamp)
        return True

    def on_camera_pose(self, raw: bytes) -> bool:
        if not self.cfg.camera.use_pose_topic:
            return False
        try:
            stamp, pose = M.parse_pose_stamped(raw, frame_id=self.cfg.frame_id)
        except M.InputError as exc:
            self.stats.reject("camera_pose", exc.reason, str(exc))
            return False
        self.camera_pose = pose
        self._arrive("camera_pose", stamp)
        return True

    def admit_cloud(self, raw: bytes) -> bool:
        """Cheap checks on arrival (size, flood); decoding happens later, off the arrival thread."""
        if len(raw) > self.cfg.limits.max_cloud_bytes:
            self.stats.reject("points", "too_large", f"{len(raw)} bytes")
            return False
        if not self.message_clock:
            # token bucket: bursts of a few clouds (transport jitter) pass, a sustained flood does not
            now, rate = self.clock(), self.cfg.limits.max_cloud_rate_hz
            self.cloud_tokens = min(3.0, self.cloud_tokens + (now - self.last_cloud_arrival) * rate)
            self.last_cloud_arrival = now
            if self.cloud_tokens < 1.0:
                self.stats.reject("points", "flood", f"more than {rate} Hz")
                return False
            self.cloud_tokens -= 1.0
        return True

    def decode_cloud(self, raw: bytes) -> Cloud:
        """Decode and validate a PointCloud2; raises InputError (the caller counts it)."""
        stamp, xyz, rgb, frame = M.parse_point_cloud(raw)
        stamp -= self.cloud_delay_ns  # when it was taken, on the poses' clock
        with self.lock:
            self._check_stamp("points", stamp, self.last_cloud_ns)
            info, pose = self.camera_info, self.camera_pose.copy()
        xyz = camera_frame_cloud(xyz, frame, self.cfg.frame_id, pose_matrix(pose))
        flat = xyz.shape[0] == 1  # unorganized: onto the grid of its CameraInfo
        if flat and info is None:
            raise M.InputError("no_camera_info", "an unorganized cloud (height 1) needs its CameraInfo")
        K, w, h = info if flat else (self._intrinsics(xyz, info), xyz.shape[1], xyz.shape[0])
        camera = make_camera(K, w, h, pose)
        if flat:
            xyz, rgb = organize_cloud(xyz, rgb, camera)
            self.stats.count("clouds_organized")
        with self.lock:
            self.last_cloud_ns = stamp
            self._see(stamp)
            self._arrive("points", stamp)
        return Cloud(stamp, xyz, rgb, camera)

    def _intrinsics(self, xyz: np.ndarray, info) -> np.ndarray:
        """K for a camera-frame cloud: CameraInfo's when it is of the cloud's image size; otherwise
        the cloud's own (:func:`service.tracking.cloud_intrinsics`, kept per image size once fitted, as
        ``deform calibrate`` does), so that a lab that records no CameraInfo, or only its depth
        sensor's, is served. Raises ``no_camera_info`` / ``cloud_size_mismatch`` when the cloud fits
        no pinhole camera."""
        h, w = xyz.shape[:2]
        if info is not None and (info[1], info[2]) == (w, h):
            return info[0]
        K = self.fitted_intrinsics.get((w, h))
        if K is None:
            K = cloud_intrinsics(xyz)  # ~2 ms at any size; a failed fit is tried again on the next cloud
            if K is not None:
                self.fitted_intrinsics[(w, h)] = K
                self.stats.count("intrinsics_from_cloud")
        if K is not None:
            return K
        if info is None:
            raise M.InputError("no_camera_info")
        raise M.InputError("cloud_size_mismatch", f"cloud {w}x{h}, camera_info {info[1]}x{info[2]}")

    def on_cloud_sync(self, raw: bytes) -> bool:
        """Message clock: decode now and fuse at the first tick at or after the cloud's stamp."""
        if not self.admit_cloud(raw):
            return False
        try:
            cloud = self.decode_cloud(raw)
            self.pending.append(cloud)
            self.pending.sort(key=lambda c: c.stamp_ns)
            return True
        except M.InputError as exc:
            self.stats.reject("points", exc.reason, str(exc))
            return False

    # ----- loop --------------------------------------------------------------------------------
    def tick(self, stamp_ns: int) -> Estimate | None:
        """Advance one period with the latest grip; None while no gripper pose has arrived. On the
        wall clock a tick whose poses fell far behind steps through those missed, one period each
        (:meth:`service.pose_timeline.PoseTimeline.next`; counted as ``pose_catch_up_steps``); where
        the grippers jumped (a gap too long for that; with ``pose_delay_s: 0`` a newest pose more than
        ``RESET_S`` on; the message clock's grid started again after a gap), the rope is stopped
        after the step."""
        with self.lock:
            if self.poses is None:
                return None
            pose_ns, poses, grip = self.poses
            samples, jumped = [(pose_ns, poses, grip)], False  # jumped: stop the rope after the step
            if self.timeline is not None:
                samples = [(t, p, grips_from_poses(p, self.cfg.grippers)) for t, p in self.timeline.next()]
                self.stats.count("pose_catch_up_steps", len(samples) - 1)
                jumped = self.timeline.jumped
            elif self.grid_ticks and self.grid_ticks[0][0] <= stamp_ns:
                while self.grid_ticks and self.grid_ticks[0][0] <= stamp_ns:
                    pose_ns, poses, restarted = self.grid_ticks.popleft()
                    jumped = jumped or restarted
                samples = [(pose_ns, poses, grips_from_poses(poses, self.cfg.grippers))]
            elif not self.message_clock and self.history:  # the newest pose each tick: far on?
                jumped = pose_ns - self.history[-1].pose_ns > RESET_S * NS
            if self.message_clock:
                self.clock_s = stamp_ns / NS
            for t, _, g in samples:
                x, observed = self._advance(g, t, still=jumped)
            pose_ns, poses, grip = samples[-1]
            while self.pending and self.pending[0].stamp_ns <= stamp_ns:
                x, observed = self._correct(self.tracker, self.pending.pop(0))
                self.fused_at = self.now()  # (message clock: no history moments to rewrite)
            self.prev_x = self.estimate.x if self.estimate is not None else None
            self.estimate = Estimate(
                pose_ns,  # the time the state describes: its grip's, not the tick's
                np.asarray(x, dtype=float),
                np.asarray(observed, dtype=bool),
                grip,
                poses,
                self.tick_index,
            )
            return self.estimate

    def _advance(self, grip: np.ndarray, pose_ns: int, still: bool = False):
        """One model step to ``grip`` (the first: the tracker's initialisation), kept in the history
        (call under ``lock``); ``still``: the grippers jumped there, the rope is stopped after the step
        (``Tracker.hold_still``; counted as ``pose_jumps``). -> the tracker's ``(x, observed)``."""
        t0 = time.perf_counter()
        with torch.no_grad():
            if not self.initialized:
                x, observed = self.tracker.initialize(grip)
                self.initialized = True
            else:
                x, observed = self.tracker.step(grip)
                self.stats.step_s.add(time.perf_counter() - t0)
                if still and hasattr(self.tracker, "hold_still"):
                    self.tracker.hold_still()
                    self.stats.count("pose_jumps")
        self.tick_index += 1
        moment = self.tracker.moment() if self.rewinds else None
        self.history.append(Tick(self.tick_index, grip, pose_ns, moment))
        return x, observed

    def fusion_tick(self, stamp_ns: int) -> Tick | None:
        """The tick a cloud taken at ``stamp_ns`` is fused at (call under ``lock``): the last whose
        poses are not newer than it by more than half a period (the oldest kept if all are), or None
        when clouds are fused where they arrive (the newest tick, the tracker as it is)."""
        if not self.rewinds or not self.history:
            return None
        limit = stamp_ns + self.cfg.dt * NS / 2
        chosen = self.history[0]
        for t in self.history:
            if t.pose_ns > limit:
                break
            chosen = t
        return chosen if chosen.moment is not None else None

    def rewrite_history(self, moments: dict[int, object]) -> None:
        """The ticks a fusion replayed now hold the fused tracker's moments (call under ``lock``):
        the next cloud goes back to what this one corrected."""
        for j, t in enumerate(self.history):
            m = moments.get(t.index)
            if m is not None:
                self.history[j] = t._replace(moment=m)

    def _correct(self, tracker, cloud: Cloud):
        t0 = time.perf_counter()
        out = tracker.correct(cloud.xyz, cloud.rgb, cloud.camera)
        self.record_fusion(cloud, time.perf_counter() - t0)
        return out

    def record_fusion(self, cloud: Cloud, seconds: float) -> None:
        """Account for a fused cloud (here or in a worker process): timing, counter, last cloud."""
        self.stats.fusion_s.add(seconds)
        self.last_cloud = cloud
        self.stats.count("clouds_fused")

    # ----- status ------------------------------------------------------------------------------
    def mode(self) -> str:
        now = self.now()
        pose_age = now - self.arrived["ee_poses"] if "ee_poses" in self.arrived else None
        if not self.initialized or pose_age is None or pose_age > self.cfg.timeouts.pose_s:
            return "waiting"
        if self.fused_at is not None and now - self.fused_at <= self.cfg.timeouts.cloud_s:
            return "tracking"
        return "open-loop"

    def rope_status(self) -> dict | None:
        """The tracker's loss and recovery counts (state tracking or lost, lost, recovered,
        redetected, since_seen_s, disagreement); None for a tracker that keeps none."""
        status = getattr(self.tracker, "status", None)
        return status() if callable(status) else None

    def status(self) -> dict:
        now = self.now()
        snap = self.stats.snapshot()
        return {
            "namespace": self.cfg.namespace,
            "mode": self.mode(),
            "clock": self.cfg.clock,
            "rate_hz": self.stats.rate_hz(),
            "target_rate_hz": self.cfg.rate_hz,
            "ticks": self.tick_index,
            "step_ms": self.stats.step_s.summary(),
            "tick_to_publish_ms": self.stats.publish_s.summary(),
            "fusion_ms": self.stats.fusion_s.summary(),
            "cloud_age_ms": self.stats.cloud_age_s.summary(),
            "predict_ms": self.stats.predict_s.summary(),
            "predict_compute_ms": self.stats.predict_compute_s.summary(),
            "deadline_misses": snap["counts"].get("deadline_misses", 0),
            "input_age_s": {k: round(now - v, 4) for k, v in self.arrived.items()},
            "last_fusion_age_s": None if self.fused_at is None else round(now - self.fused_at, 4),
            "rope": self.rope_status(),
            "rejected": snap["rejected"],
            "dropped": snap["dropped"],
            "counts": snap["counts"],
            "tracker": type(self.tracker).__name__,
            "step": "compiled" if getattr(self.tracker, "step_fn", None) is not None else "eager",
            "step_redone": getattr(self.step_fn, "redone", 0),  # compiled steps redone eagerly (unconverged)
        }
