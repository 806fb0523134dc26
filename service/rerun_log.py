"""Rerun logging of the rope, the fused cloud, the observed flags, the grippers and the timings, on a
``message_time`` timeline. A separate thread with a bounded queue does the logging so that a slow
sink can only drop log entries, never delay the tick."""

from __future__ import annotations

import logging
import queue
import threading

import numpy as np

from service.config import RerunSettings
from service.geometry import quat_to_matrix

log = logging.getLogger("deform.service")
NS = 1_000_000_000


def blueprint():
    """The layout a user opens to: the rope in 3D beside the loop's timings, the observed and
    unexplained fractions, and the mode changes and rope losses."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="rope", origin="/world"),
            rrb.Vertical(
                rrb.TimeSeriesView(name="timing [ms]", origin="/timing"),
                rrb.TimeSeriesView(name="rope: observed, unexplained", origin="/rope"),
                rrb.TextLogView(name="mode", origin="/status"),
            ),
            column_shares=[2, 1],
        ),
        collapse_panels=True,
    )


class RerunLogger(threading.Thread):
    def __init__(self, settings: RerunSettings, namespace: str, stats=None):
        super().__init__(name=f"rerun[{namespace}]", daemon=True)
        import rerun as rr

        self.rr = rr
        self.settings = settings
        self.stats = stats
        self.rec = rr.RecordingStream("deform_service_" + namespace.replace("/", "_"))
        if settings.mode == "file":
            self.rec.save(settings.path, default_blueprint=blueprint())
        elif settings.mode == "connect":  # a viewer on another machine: `rerun --serve` or the app
            self.rec.connect_grpc(settings.url, default_blueprint=blueprint())
        else:
            self.rec.spawn(default_blueprint=blueprint())
        self.queue: queue.Queue = queue.Queue(maxsize=256)
        self._clouds = 0
        self._last_mode = None
        self._rope_counts = (0, 0)
        self._length_scale = 1.0

    def submit(self, kind: str, *payload) -> None:
        try:
            self.queue.put_nowait((kind, payload))
        except queue.Full:
            if self.stats is not None:
                self.stats.drop("rerun_log_entry")

    def close(self) -> None:
        self.queue.put(("stop", ()))
        self.join(timeout=10)
        self.rec.flush()
        self.rec.disconnect()

    def run(self) -> None:
        while True:
            kind, payload = self.queue.get()
            if kind == "stop":
                return
            try:
                getattr(self, "_log_" + kind)(*payload)
            except Exception:
                log.exception("rerun logging failed")

    def _time(self, stamp_ns: int) -> None:
        self.rec.set_time("message_time", timestamp=stamp_ns / NS)

    def _log_estimate(
        self, est, step_ms: float | None, publish_ms: float | None, mode: str, rope: dict | None = None
    ) -> None:
        rr, rec = self.rr, self.rec
        self._time(est.stamp_ns)
        colors = np.where(est.observed[:, None], [[40, 200, 80]], [[230, 80, 60]]).astype(np.uint8)
        rec.log("world/rope", rr.LineStrips3D([est.x], colors=[[240, 200, 60]], radii=0.004))
        rec.log("world/rope/vertices", rr.Points3D(est.x, colors=colors, radii=0.008))
        axes = quat_to_matrix(est.poses[:, 3:])[:, :, 0]
        rec.log(
            "world/grippers",
            rr.Arrows3D(origins=est.poses[:, :3], vectors=0.08 * axes, colors=[[80, 140, 255]]),
        )
        rec.log("world/grippers/gripped", rr.Points3D(est.grip, colors=[[80, 140, 255]], radii=0.01))
        rec.log("rope/observed_fraction", rr.Scalars(float(est.observed.mean())))
        if step_ms is not None:
            rec.log("timing/step_ms", rr.Scalars(step_ms))
        if publish_ms is not None:
            rec.log("timing/tick_to_publish_ms", rr.Scalars(publish_ms))
        if mode != self._last_mode:
            rec.log("status/mode", rr.TextLog(f"mode: {mode}"))
            self._last_mode = mode
        if rope is not None:
            self._log_rope(rope)

    def _log_rope(self, rope: dict) -> None:
        """The share of unexplained rope points, how far the camera puts the rope from the model's
        shape, and a line whenever the rope is lost or found, or the camera's length of the rope
        replaces the model's."""
        rr, rec = self.rr, self.rec
        if rope.get("disagreement") is not None:
            rec.log("rope/unexplained_fraction", rr.Scalars(float(rope["disagreement"])))
        if rope.get("camera_over_model_mm") is not None:
            rec.log("rope/camera_over_model_mm", rr.Scalars(float(rope["camera_over_model_mm"])))
        counts = (rope["lost"], rope["recovered"])
        if counts != self._rope_counts:
            if rope["lost"] > self._rope_counts[0]:
                rec.log("status/rope", rr.TextLog(f"rope lost ({rope['lost']} so far)", level="WARN"))
            if rope["recovered"] > self._rope_counts[1]:
                how = f"{rope['redetected']} re-detections from the cloud alone"
                rec.log("status/rope", rr.TextLog(f"rope found again ({rope['recovered']} so far; {how})"))
            self._rope_counts = counts
        scale = rope.get("length_scale")
        if scale is not None and scale != self._length_scale:
            rec.log("rope/length_scale", rr.Scalars(float(scale)))
            rec.log(
                "status/rope",
                rr.TextLog(
                    f"the camera's rope length replaced the model's: {scale:.3f}x its rest length",
                    level="WARN",
                ),
            )
            self._length_scale = scale

    def _log_cloud(self, cloud) -> None:
        self._clouds += 1
        if (self._clouds - 1) % self.settings.cloud_every:
            return
        self._time(cloud.stamp_ns)
        keep = np.isfinite(cloud.xyz).all(axis=-1)
        world = cloud.camera.to_world(cloud.xyz[keep])
        self.rec.log("world/cloud", self.rr.Points3D(world, colors=cloud.rgb[keep], radii=0.002))

    def _log_truth(self, stamp_ns: int, x: np.ndarray) -> None:
        self._time(stamp_ns)
        self.rec.log("world/ground_truth", self.rr.LineStrips3D([x], colors=[[200, 200, 200]], radii=0.002))
