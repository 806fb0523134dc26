"""Perception settings in one place, so tests and the service can override them. The dataclasses hold
the defaults; ``config/perception.yaml`` lists them as a starting point for a settings file.

Plain dataclasses: the YAML has sections ``segmentation``, ``estimation``, ``tracker`` and ``render``;
unknown keys are an error so that typos do not silently fall back to defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import yaml


@dataclass
class SegmentationConfig:
    hsv_low: tuple[int, int, int] = (5, 120, 60)  # OpenCV HSV, H in 0..180
    hsv_high: tuple[int, int, int] = (25, 255, 255)
    depth_min: float = 0.25  # m, camera z
    depth_max: float = 3.0
    # colour spilled off the rope (perception.segment.front_surface): in an organized cloud, a
    # rope-coloured pixel more than spill_margin behind the nearest rope-coloured pixel within
    # spill_window pixels is dropped (0: off)
    spill_window: int = 4
    spill_margin: float = 0.05  # m; beyond a noisy sensor's spread over one rope's width


@dataclass
class EstimationConfig:
    max_points: int = 2_500_000  # larger clouds are decimated (pixel stride) before segmentation. Not
    # less: a thin rope far off is a line a pixel or two wide that a stride of 2 leaves a sixth of
    # (the colour mask of a 1280x720 cloud costs ~1.5 ms; what follows scales with the rope's pixels)
    voxel: float = 0.008  # m, voxel grid downsampling of the rope points
    filter_radius: float = 0.08  # m, keep points this close to a predicted vertex
    occlusion_margin: float = 0.03  # m, a vertex is occluded if the scene is this much closer than it
    occlusion_window: int = 1  # half size of the pixel window for the observed depth
    occlusion_noise: float = 5.0  # the occlusion margin is at least this many times the depth noise the
    # cloud shows around the rope's depth (perception.cloud.depth_noise): the nearest of a window of
    # noisy depths lies ~2 sigma in front of the rope's surface, which lies a radius in front of the
    # vertex (0: the fixed margin alone)
    dbscan_eps: float = 0.025  # m
    dbscan_min_samples: int = 3
    assoc_radius: float = 0.05  # m, a vertex joins the group of its nearest point within this
    gmm_iters: int = 8
    gmm_sigma: float = 0.02  # m, initial isotropic std of the components
    min_points: float = 3.0  # responsibility mass a component needs to count as observed
    two_sided: float = (
        0.25  # support on both sides of a vertex along the rope, as a fraction of the half edge
    )
    surface_offset: float = 0.004  # m, points lie on the camera-facing surface: push means back by this
    bend_centroid: float = 1.0  # share of the offset of a component's mean inside the bend (the centroid
    # of an arc lies inside it) that is taken back (perception.estimate.arc_centroid_offset; 0: none)
    along_rope: float = 0.5  # share of a correction's component along the rope that is applied (0: only
    # across it). A rope without features shows where it lies across, not how far along it a vertex sits:
    # that component of a GMM mean comes partly from the components sharing evenly spread points. Half
    # (tracking_peers, ours only, same clouds): 2.38 -> 1.89 mm unoccluded, 4.33 -> 4.04 at 50 %, table
    # contact 1.37x the no-contact error; none: 1.70 and 3.92 mm, but the no-contact error fell more
    # than the contact one (1.63x)
    repeat_beyond: float = 0.02  # m: a correction that moved a vertex farther than this is made again from
    # where it ended (one EM pass from a far prediction stops short of the rope; 0: never)
    unhide: bool = True  # a vertex hidden by a surface no closer than its observed neighbours (the model put
    # it inside a table or post it does not know, not behind an occluder) is looked for in that second pass
    # (and in up to two more while they find such vertices: perception.estimate.MORE_UNHIDE_PASSES)


@dataclass
class TrackerConfig:
    stale_after_s: float = 0.2  # observed flags expire when no camera update came for this long
    settle_max_steps: int = 300
    settle_tol: float = 1e-3  # m/s
    init_em_rounds: int = 3
    rope_radius: float = 0.005  # m
    velocity_gain: float = (
        0.5  # corrections also nudge velocities: v += gain * shift / time since last update
    )
    lost_fraction: float = 0.3  # lost when this share of the visible rope points is beyond filter_radius
    lost_after_s: float = 0.5  # ... or when no cloud showed the rope for this long
    min_seen_points: int = 10  # rope voxels a cloud needs for the rope to count as seen
    redetect_gain: float = 0.8  # a shape found from the cloud alone replaces the estimate when its
    # capped mean point distance is below this fraction of the estimate's
    refind_cost: float = 0.012  # m: a corrected estimate whose points lie farther than this on average
    # (capped at filter_radius; the near surface alone is ~ a rope radius) is checked against the shape
    # the cloud alone gives (0: never)
    refind_seen: float = 0.9  # ... and replaced by it only when this share of its free vertices has
    # rope points within assoc_radius (a hidden stretch is bridged straight: there the model knows better)
    length_gain: float = 0.1  # weight of each cloud that shows the free rope whole in the running
    # measure of its length against the rest length (perception.length; 0: the model's length is kept)
    length_trigger: float = 0.015  # the rest lengths take the camera's length when the two differ by more
    length_bounds: tuple[float, float] = (0.8, 1.25)  # ... within these factors of the starting rest length
    coherence: float = 1.0  # share of the shift interpolated from the corrected neighbours that a visible
    # vertex the correction left alone takes (a vertex beyond the association radius of a rope the model
    # lost hold of; 0: none)
    hidden_coherence: float = 1.0  # share of the same interpolated shift that a hidden free vertex takes,
    # in position only (not in velocity: velocity_gain): the model's error in a hidden stretch is mostly
    # the error the camera shows beside it. tracking_peers (ours): 25 % occluded 1.9 -> 1.8 mm, 50 %
    # 3.1 -> 2.9 (0: hidden vertices keep the model's prediction)
    camera_residual: float = 1.0  # share of the correction across the rope at the observed vertices
    # that the estimate keeps beyond the state's projection onto the rest lengths (0: the model state;
    # 1: the camera across the rope, which beats the model there once bend_centroid takes its bias back)


@dataclass
class RenderConfig:
    scale: float = 0.5  # of the Azure Kinect NFOV 640x576 resolution
    rope_radius: float = 0.005
    rope_rgb: tuple[int, int, int] = (230, 110, 25)
    table_rgb: tuple[int, int, int] = (165, 155, 145)
    gripper_rgb: tuple[int, int, int] = (50, 50, 55)
    occluder_rgb: tuple[int, int, int] = (95, 110, 135)
    table_z: float = 0.0
    camera_distance: float = 1.0  # m from the scene centre
    camera_elevation_deg: float = 35.0
    camera_azimuth_deg: float = 0.0  # turned about the vertical from the view square on to the rope
    noise_base: float = 0.001  # m, depth noise std = base + quad * z^2
    noise_quad: float = 0.0015
    edge_jump: float = 0.02  # m, depth jump that invalidates the far pixel of an edge
    edge_fg_drop: float = 0.1  # probability of also dropping a near-side edge pixel
    dropout: float = 0.002  # random missing pixels
    color_noise: float = 6.0
    # Two artefacts of real RGB-D sensors, off by default (the stored benchmarks render without them):
    flying_pixels: float = 0.0  # share of the far pixels of a depth edge kept at a depth between the
    # two surfaces (mixed pixels) instead of being lost
    color_shift_px: int = 0  # colour registered this many pixels off the depth along the image rows
    # (the colour camera's calibration to the depth camera): the rope's colour spills onto what lies
    # beside it and beyond it
    occlusion: float = 0.0  # fraction of the rope hidden by the occluder
    occlusion_start: float = 0.3  # of the recording
    occlusion_end: float = 0.8
    occluder_gap: float = 0.15  # m between occluder and rope, towards the camera
    blackout_start_s: float = 1.5  # s into the recording: an occluder hides the whole rope from here ...
    blackout_s: float = 0.0  # ... for this long (0: no blackout)


@dataclass
class PerceptionConfig:
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    estimation: EstimationConfig = field(default_factory=EstimationConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    render: RenderConfig = field(default_factory=RenderConfig)


def _section(cls, values: dict):
    names = {f.name for f in fields(cls)}
    unknown = set(values) - names
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown keys {sorted(unknown)}")
    out = cls()
    for k, v in values.items():
        out = replace(out, **{k: tuple(v) if isinstance(v, list) else v})
    return out


def load_config(source: str | Path | dict | PerceptionConfig | None = None) -> PerceptionConfig:
    """A :class:`PerceptionConfig` from a YAML path, a dict, an instance, or None (the defaults of the
    dataclasses above, which ``config/perception.yaml`` lists; a test keeps the two equal).

    Args:
        source: a YAML path, a dict of sections, a :class:`PerceptionConfig`, or None.

    Returns:
        The :class:`PerceptionConfig`.

    Raises:
        ValueError: an unknown section or key (typos never fall back to defaults silently).
    """
    if isinstance(source, PerceptionConfig):
        return source
    if source is None:
        return PerceptionConfig()
    data = source if isinstance(source, dict) else (yaml.safe_load(Path(source).read_text()) or {})
    sections = {f.name: f.type for f in fields(PerceptionConfig)}
    unknown = set(data) - set(sections)
    if unknown:
        raise ValueError(f"perception config: unknown sections {sorted(unknown)}")
    kinds = {
        "segmentation": SegmentationConfig,
        "estimation": EstimationConfig,
        "tracker": TrackerConfig,
        "render": RenderConfig,
    }
    return PerceptionConfig(**{name: _section(kinds[name], data.get(name) or {}) for name in kinds})
