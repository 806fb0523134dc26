"""How a lab films its calibration clips: camera placement and rate, the rope's colour, the camera's
noise, how much an occluder hides. The benchmark's default is one such lab (``session``); others
check that `deform calibrate` is not tuned to it (issue 49: the acceptance runs on a renderer, a rope
colour and topics that we do not have).

A setup reaches `deform calibrate` only as a user's would: through the bags (clouds at the
camera's rate, its intrinsics and pose as ``deform-service record`` writes them) and a perception
settings file holding the rope's colour range (``--perception``). Nothing else of it is passed.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml

from benchmarks.tracking.scenarios import SENSOR


@dataclass(frozen=True)
class Setup:
    """One lab's way of filming. Angles in degrees, distances in metres.

    ``azimuth_deg``: the camera turned about the vertical from the view perpendicular to the rope's
    first gripper-to-gripper direction (0: square on; a lab rarely is). ``occluded``: the share of the
    rope an occluder hides in every ``occluded_every``-th clip (from the second on)."""

    name: str
    fps: float = 30.0
    distance_m: float = 1.2
    elevation_deg: float = 30.0
    azimuth_deg: float = 0.0
    scale: float = 0.5  # of the Azure Kinect NFOV 640x576 resolution
    rope_rgb: tuple[int, int, int] = (230, 110, 25)
    hsv_low: tuple[int, int, int] | None = None  # the colour range a user gives; None: the default
    hsv_high: tuple[int, int, int] | None = None
    noise_base: float = 0.001
    noise_quad: float = 0.0015
    dropout: float = 0.002
    occluded: float = 0.25
    occluded_every: int = 2
    color_shift_px: int = 0  # the colour registered this many pixels off the depth
    flying_pixels: float = 0.0  # share of the far pixels of depth edges at a mixed depth

    def perception(self):
        """Perception's settings for this lab: its renderer (rate aside) and its colour range."""
        from perception import load_config

        p = load_config(None)
        render = replace(
            p.render,
            scale=self.scale,
            rope_rgb=self.rope_rgb,
            camera_distance=self.distance_m,
            camera_elevation_deg=self.elevation_deg,
            camera_azimuth_deg=self.azimuth_deg,
            noise_base=self.noise_base,
            noise_quad=self.noise_quad,
            dropout=self.dropout,
            color_shift_px=self.color_shift_px,
            flying_pixels=self.flying_pixels,
        )
        seg = p.segmentation
        if self.hsv_low is not None:
            seg = replace(seg, hsv_low=self.hsv_low, hsv_high=self.hsv_high)
        return replace(p, render=render, segmentation=seg)

    def occlusion_of_clip(self, i: int) -> float:
        """The share of the rope hidden in clip ``i``."""
        return self.occluded if i % self.occluded_every == self.occluded_every - 1 else 0.0

    def settings_file(self, out: Path) -> Path | None:
        """The perception settings file a user of this lab passes (``--perception``): the rope's
        colour range only; None when the default range serves."""
        if self.hsv_low is None:
            return None
        path = out / "rope_colour.yaml"
        seg = {"hsv_low": list(self.hsv_low), "hsv_high": list(self.hsv_high)}
        path.write_text(yaml.safe_dump({"segmentation": seg}))
        return path


SETUPS = {
    # the benchmark's lab: a Kinect-like camera at 30 Hz, 1.2 m from the motion, 30 degrees down,
    # square on; an orange rope; a quarter of the rope hidden in every other clip
    "session": Setup("session"),
    # another lab: a camera streaming at 15 Hz (half the bandwidth), farther and higher (1.6 m, 50
    # degrees down) and 35 degrees off square, at three quarters of the resolution, noisier depth and
    # more dropouts; a blue rope given by its colour range; a third of the rope hidden in every third clip
    "other_lab": Setup(
        "other_lab",
        fps=15.0,
        distance_m=1.6,
        elevation_deg=50.0,
        azimuth_deg=35.0,
        scale=0.75,
        rope_rgb=(35, 95, 205),
        hsv_low=(95, 120, 50),
        hsv_high=(125, 255, 255),
        noise_base=0.002,
        noise_quad=0.0025,
        dropout=0.01,
        occluded=0.35,
        occluded_every=3,
    ),
    # the benchmark's lab with a camera whose colour is registered 2 px off its depth and whose depth
    # edges give mixed pixels (half the far pixels of an edge at a depth between the two surfaces):
    # the rope's colour spills onto the table and the air behind it
    "sensor": Setup("sensor", **SENSOR),  # the tracking benchmark's sensor clouds
}


def session_camera(setup: Setup, positions: list[np.ndarray]):
    """One camera for the session, placed once to see all of its motion (perception's
    :func:`default_camera` with the lab's place: ``distance_m`` from the centre of the motion,
    ``elevation_deg`` down, ``azimuth_deg`` off the view square on to the first clip's
    gripper-to-gripper direction)."""
    from perception import default_camera

    return default_camera(np.concatenate(positions, axis=0), setup.perception().render)
