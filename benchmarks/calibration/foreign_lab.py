"""A second, independent lab: its own renderer, sensor model, conventions and rosbag2 writer.

``deform calibrate`` had only been run on bags from the project's own renderer
(``perception.render``) and bag writer (``service.bag``): a bag that agrees with our reader because
both sides were written from the same assumptions proves little. This module shares no code with
either. It is written from the ROS message definitions and from how an RGB-D camera measures, the
way another lab's camera driver and ``ros2 bag record`` would produce data:

* an active-stereo / structured-light depth sensor (depth from a quantized, noisy disparity;
  projector shadows, grazing-angle and speckle dropouts; missing points written as (0, 0, 0) as a
  RealSense driver writes them), colour registered to depth, with shading, gamma and noise;
* a RealSense-like driver's topics (``/camera/depth/color/points``, colour and depth CameraInfo of
  different sizes, an optical frame at the end of a ``/tf_static`` chain);
* a robot publishing its TCP poses at 125 Hz in its own ``base_link`` frame, with a TCP 1.5 cm
  outside the rope and an arbitrary, slowly varying roll.

The acceptance of ``deform calibrate`` runs on these bags: a renderer and topic names we do not have.
Only :mod:`service.config` is shared (the written ``service.yaml`` must be the service's format).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import open3d as o3d
import yaml
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore
from scipy.interpolate import make_interp_spline

from service.config import GripOffsets, Grippers

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
START_NS = 1_750_000_000 * 1_000_000_000  # the first message's stamp

POSES_TOPIC = "/robot/tcp_poses"
POINTS_TOPIC = "/camera/depth/color/points"
COLOR_INFO_TOPIC = "/camera/color/camera_info"
DEPTH_INFO_TOPIC = "/camera/depth/camera_info"
TF_STATIC_TOPIC = "/tf_static"
WORLD, BASE, CAMERA_LINK = "world", "base_link", "camera_link"
COLOR_OPTICAL, DEPTH_OPTICAL = "camera_color_optical_frame", "camera_depth_optical_frame"

# the robot's base in the world: 0.35 m, -0.55 m, turned 90 degrees about z
WORLD_FROM_BASE_XYZ = (0.35, -0.55, 0.0)
WORLD_FROM_BASE_YAW_DEG = 90.0
# a body frame (x forward, y left, z up) to an optical frame (z forward, x right, y down)
LINK_FROM_OPTICAL_Q = (-0.5, 0.5, -0.5, 0.5)

# what a pixel saw (render_frame's labels)
NOTHING, TABLE, WALL, ROPE, GRIPPER, OCCLUDER = 0, 1, 2, 3, 4, 5


@dataclass(frozen=True)
class ForeignLab:
    """The lab: camera, sensor, robot and scene. Lengths in metres, angles in degrees."""

    width: int = 424  # a RealSense-like depth stream aligned to colour
    height: int = 240
    hfov_deg: float = 69.0
    cx_offset_px: float = 3.2  # principal point off the image centre, as calibrated cameras have it
    cy_offset_px: float = -2.1
    distance_m: float = 1.0  # camera from the centre of the motion
    elevation_deg: float = 40.0
    azimuth_deg: float = -20.0
    fps: float = 30.0
    stamp_jitter_s: float = 0.002
    stamp_delay_s: float = 0.0  # clouds stamped this long after capture (a driver stamping on arrival)
    drop_share: float = 0.02  # clouds the driver drops
    pose_hz: float = 125.0  # the robot publishes its poses at 125 Hz, not 100
    tcp_offset_m: float = 0.015  # the TCP sits this far outward of the end marker (d0)
    rope_axis: str = "x"  # the gripper frame's axis the rope runs along ("x", "y" or "z")
    rope_radius_m: float = 0.006
    rope_rgb: tuple = (40, 170, 70)  # a green rope
    # OpenCV HSV (H in 0..180) a user would give for this rope under this lighting
    hsv_low: tuple = (45, 90, 60)
    hsv_high: tuple = (85, 255, 255)
    occluded_every: int = 2  # every second clip has an arm passing in front of the rope
    occluded_share: float = 0.3
    # the sensor: active stereo, projector offset by the baseline along the optical +x
    baseline_m: float = 0.05  # 0: an ideal sensor (no projector shadows, no disparity noise)
    disparity_sigma_px: float = 0.08
    disparity_step_px: float = 1.0 / 8.0
    max_range_m: float = 3.0
    grazing_deg: float = 80.0
    speckle_share: float = 0.005
    colour_sigma: float = 4.0
    gamma: float = 2.2
    # the depth stream's own CameraInfo (published beside the aligned one, never used by the clouds)
    depth_width: int = 848
    depth_height: int = 480
    depth_hfov_deg: float = 87.0

    @property
    def fx(self) -> float:
        return (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def cx(self) -> float:
        """ROS/OpenCV: integer pixel coordinates are pixel centres."""
        return (self.width - 1) / 2.0 + self.cx_offset_px

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2.0 + self.cy_offset_px

    def K(self) -> np.ndarray:
        """The colour (= aligned depth) camera matrix, ROS convention."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fx, self.cy], [0.0, 0.0, 1.0]])

    def depth_K(self) -> np.ndarray:
        f = (self.depth_width / 2.0) / math.tan(math.radians(self.depth_hfov_deg) / 2.0)
        return np.array(
            [
                [f, 0.0, (self.depth_width - 1) / 2.0 - 1.3],
                [0.0, f, (self.depth_height - 1) / 2.0 + 0.8],
                [0, 0, 1],
            ]
        )


@dataclass(frozen=True)
class Room:
    """The static scene of a clip: a horizontal table at ``table_z`` and a vertical wall through
    ``wall_point`` facing the camera along ``wall_normal`` (world frame)."""

    table_z: float
    wall_point: np.ndarray
    wall_normal: np.ndarray


@dataclass(frozen=True)
class Occluder:
    """A forearm: a capped cylinder from ``tip`` to ``root`` (world frame)."""

    tip: np.ndarray
    root: np.ndarray
    radius: float = 0.04
    rgb: tuple = (212, 160, 128)  # skin


@dataclass(frozen=True)
class Frame:
    """One rendered frame: ``xyz`` (H, W, 3) float32 optical frame, missing (0, 0, 0); ``rgb`` (H, W, 3)
    uint8; ``label`` (H, W) what each pixel saw (TABLE, WALL, ROPE, GRIPPER, OCCLUDER, NOTHING)."""

    xyz: np.ndarray
    rgb: np.ndarray
    label: np.ndarray


# ----------------------------------------------------------------------------------------- rotations


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _matrix_of_quat(q) -> np.ndarray:
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _quat_of_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (x, y, z, w), w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    m = np.array([np.trace(R), R[0, 0], R[1, 1], R[2, 2]])
    i = int(np.argmax(m))
    if i == 0:
        w = 0.5 * math.sqrt(1.0 + m[0])
        q = [(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w]
    elif i == 1:
        x = 0.5 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [x, (R[0, 1] + R[1, 0]) / (4 * x), (R[0, 2] + R[2, 0]) / (4 * x), (R[2, 1] - R[1, 2]) / (4 * x)]
    elif i == 2:
        y = 0.5 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / (4 * y), y, (R[1, 2] + R[2, 1]) / (4 * y), (R[0, 2] - R[2, 0]) / (4 * y)]
    else:
        z = 0.5 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / (4 * z), (R[1, 2] + R[2, 1]) / (4 * z), z, (R[1, 0] - R[0, 1]) / (4 * z)]
    q = np.asarray(q)
    q = q / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def _transform(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _inverse(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return _transform(R.T, -R.T @ t)


def world_from_base() -> np.ndarray:
    """The robot base in the world (the first link of the lab's /tf_static chain)."""
    return _transform(_rot_z(WORLD_FROM_BASE_YAW_DEG), WORLD_FROM_BASE_XYZ)


def _pose_of(T: np.ndarray) -> np.ndarray:
    return np.concatenate([T[:3, 3], _quat_of_matrix(T[:3, :3])])


def _matrix_of_pose(p) -> np.ndarray:
    return _transform(_matrix_of_quat(p[3:7]), p[:3])


# ------------------------------------------------------------------------------------------ geometry


def place_camera(positions: np.ndarray, lab: ForeignLab) -> np.ndarray:
    """4x4 world_from_optical transform of a camera looking at the centre of the motion positions
    (T, n, 3) (world frame, z up, gravity -z), distance/elevation/azimuth as in the lab (azimuth 0:
    the camera on the -y side looking along +y). Optical frame convention of ROS: z forward, x right,
    y down."""
    centre = np.asarray(positions, dtype=float).reshape(-1, 3).mean(axis=0)
    el, az = math.radians(lab.elevation_deg), math.radians(lab.azimuth_deg)
    back = np.array([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
    eye = centre + lab.distance_m * back
    z = -back
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return _transform(np.stack([x, y, z], axis=1), eye)


def make_room(positions: np.ndarray, world_from_optical: np.ndarray) -> Room:
    """A clip's table (5 cm below the lowest marker of the whole clip) and the wall 1.2 m beyond the
    centre of its motion, seen from the camera."""
    p = np.asarray(positions, dtype=float).reshape(-1, 3)
    centre = p.mean(axis=0)
    h = centre - world_from_optical[:3, 3]
    h[2] = 0.0
    h /= np.linalg.norm(h)
    return Room(float(p[:, 2].min() - 0.05), centre + 1.2 * h, -h)


def _roll(t, phase: float) -> np.ndarray:
    """The gripper's roll about its +x axis: arbitrary, slow and smooth [rad]."""
    t = np.asarray(t, dtype=float)
    return phase + 0.6 * np.sin(2 * np.pi * 0.13 * t + phase) + 0.15 * t


def _end_edges(x: np.ndarray) -> list[np.ndarray]:
    """(..., n, 3) markers -> the unit end edges (..., 3) of the first (0 -> 1) and last (n-1 -> n-2)
    gripper: each gripper's +x."""
    out = []
    for i0, i1 in ((0, 1), (-1, -2)):
        e = x[..., i1, :] - x[..., i0, :]
        out.append(e / np.linalg.norm(e, axis=-1, keepdims=True))
    return out


def roll_references(positions: np.ndarray) -> np.ndarray:
    """(T, n, 3) a clip's markers -> (T, 2, 3) for each gripper a direction normal to its end edge,
    carried along the clip by parallel transport: the zero of its roll, smooth however the edge turns
    (a fixed world axis would flip where the edge passes it)."""
    positions = np.asarray(positions, dtype=float)
    refs = np.empty((len(positions), 2, 3))
    for k, ex in enumerate(_end_edges(positions)):
        e = np.cross([0.0, 0.0, 1.0] if abs(ex[0, 2]) < 0.9 else [1.0, 0.0, 0.0], ex[0])
        for j in range(len(positions)):
            e = e - np.dot(e, ex[j]) * ex[j]
            e /= np.linalg.norm(e)
            refs[j, k] = e
    return refs


def gripper_poses(x: np.ndarray, t, lab: ForeignLab, refs: np.ndarray | None = None) -> np.ndarray:
    """(..., n, 3) marker positions at times ``t`` (...) [s] -> (..., 2, 7) world-frame TCP poses
    (x y z qx qy qz qw) of the first and last gripper: the ``rope_axis`` (+x) along the end edge into the rope (from
    marker 0 to 1, from n-1 to n-2), the TCP ``tcp_offset_m`` outward of the end marker, a slowly
    varying roll about that axis from ``refs`` (..., 2, 3) (:func:`roll_references`; default: a world axis)."""
    x = np.asarray(x, dtype=float)
    t = np.broadcast_to(np.asarray(t, dtype=float), x.shape[:-2])
    out = np.empty(x.shape[:-2] + (2, 7))
    for k, (ex, i0, phase) in enumerate(zip(_end_edges(x), (0, -1), (0.4, -1.1))):
        if refs is None:
            ref = np.cross(np.where(np.abs(ex[..., 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]), ex)
        else:
            ref = np.asarray(refs, dtype=float)[..., k, :]
        e1 = ref - (ref * ex).sum(-1, keepdims=True) * ex
        e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = np.cross(ex, e1)
        r = _roll(t, phase)[..., None]
        ey = np.cos(r) * e1 + np.sin(r) * e2
        ez = np.cross(ex, ey)
        columns = {"x": (ex, ey, ez), "y": (ez, ex, ey), "z": (ey, ez, ex)}[lab.rope_axis]
        R = np.stack(columns, axis=-1).reshape(-1, 3, 3)  # right-handed: cyclic permutations
        q = np.array([_quat_of_matrix(Ri) for Ri in R])
        for j in range(1, len(q)):  # one sign along the motion: a smooth quaternion stream
            if np.dot(q[j], q[j - 1]) < 0:
                q[j] = -q[j]
        out[..., k, :3] = x[..., i0, :] - lab.tcp_offset_m * ex
        out[..., k, 3:] = q.reshape(x.shape[:-2] + (4,))
    return out


def _centreline(x: np.ndarray, samples: int = 160) -> np.ndarray:
    """A smooth curve through the markers: cubic spline over the chord-length parameter."""
    x = np.asarray(x, dtype=float)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(x, axis=0), axis=1))])
    return make_interp_spline(s, x, k=3)(np.linspace(0.0, s[-1], samples))


def _tube(c: np.ndarray, radius: float, sides: int = 14) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed tube along the polyline c (m, 3): vertices, vertex normals, triangles."""
    m = len(c)
    tan = np.gradient(c, axis=0)
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) if abs(tan[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    nrm = np.empty_like(c)
    nrm[0] = np.cross(tan[0], ref)
    nrm[0] /= np.linalg.norm(nrm[0])
    for i in range(1, m):  # parallel transport of the section's frame
        v = nrm[i - 1] - np.dot(nrm[i - 1], tan[i]) * tan[i]
        nrm[i] = v / np.linalg.norm(v)
    bin_ = np.cross(tan, nrm)
    a = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(a)[None, :, None] * nrm[:, None, :] + np.sin(a)[None, :, None] * bin_[:, None, :]
    verts = (c[:, None, :] + radius * ring).reshape(-1, 3)
    normals = ring.reshape(-1, 3)
    i = np.arange(m - 1)[:, None]
    j = np.arange(sides)[None, :]
    v00, v01 = i * sides + j, i * sides + (j + 1) % sides
    v10, v11 = v00 + sides, v01 + sides
    tris = np.concatenate(
        [np.stack([v00, v10, v11], -1).reshape(-1, 3), np.stack([v00, v11, v01], -1).reshape(-1, 3)]
    )
    # caps: their own ring vertices, with axial normals
    caps_v, caps_n, caps_t = [verts], [normals], [tris]
    base = len(verts)
    for end, sign in ((0, -1.0), (m - 1, 1.0)):
        rv = c[end] + radius * ring[end]
        cv = np.concatenate([rv, c[end][None]])
        caps_v.append(cv)
        caps_n.append(np.repeat(sign * tan[end][None], sides + 1, axis=0))
        k = np.arange(sides)
        caps_t.append(np.stack([base + k, base + (k + 1) % sides, np.full(sides, base + sides)], -1))
        base += sides + 1
    return np.concatenate(caps_v), np.concatenate(caps_n), np.concatenate(caps_t)


def _box(centre, axes: np.ndarray, size) -> tuple[np.ndarray, np.ndarray]:
    """A box: centre, axes (3, 3) columns, full edge lengths along them -> vertices, triangles."""
    s = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float) - 0.5
    verts = np.asarray(centre) + (s * np.asarray(size)) @ np.asarray(axes).T
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return verts, tris


def _quad(corner, e1, e2) -> tuple[np.ndarray, np.ndarray]:
    corner, e1, e2 = (np.asarray(v, dtype=float) for v in (corner, e1, e2))
    verts = np.array([corner, corner + e1, corner + e1 + e2, corner + e2])
    return verts, np.array([[0, 1, 2], [0, 2, 3]])


def _gripper_boxes(pose: np.ndarray, lab: ForeignLab) -> list[tuple[np.ndarray, np.ndarray, tuple]]:
    """Two fingers (4 x 1 x 2 cm) either side of the rope's end edge and a palm behind them."""
    R = _matrix_of_quat(pose[3:7])
    p = pose[:3]
    ex, ey = R[:, 0], R[:, 1]
    gap = lab.rope_radius_m + 0.001 + 0.005  # half the opening plus half a finger's thickness
    out = []
    for side in (-1.0, 1.0):
        out.append((*_box(p + 0.02 * ex + side * gap * ey, R, (0.04, 0.01, 0.02)), (74, 76, 82)))
    out.append((*_box(p - 0.02 * ex, R, (0.03, 0.06, 0.045)), (42, 42, 46)))
    out.append((*_box(p - 0.06 * ex, R, (0.05, 0.045, 0.045)), (30, 30, 33)))  # the wrist flange
    return out


# ------------------------------------------------------------------------------------------ renderer


@lru_cache(maxsize=8)
def _pixel_rays(lab: ForeignLab) -> np.ndarray:
    """(H, W, 3) optical-frame rays ((u - cx)/fx, (v - cy)/fy, 1) through pixel centres (integer u, v)."""
    u, v = np.meshgrid(np.arange(lab.width, dtype=float), np.arange(lab.height, dtype=float))
    return np.stack([(u - lab.cx) / lab.fx, (v - lab.cy) / lab.fx, np.ones_like(u)], axis=-1)


def _srgb_to_linear(c) -> np.ndarray:
    return (np.asarray(c, dtype=float) / 255.0) ** 2.2


def _wood(p: np.ndarray) -> np.ndarray:
    """Linear albedo of a wooden table top at world points p (k, 3): planks along x, grain, seams."""
    x, y = p[:, 0], p[:, 1]
    plank = np.floor(y / 0.14)
    tone = 0.9 + 0.12 * np.sin(plank * 12.9898) ** 2
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (y * 23.0 + 0.7 * np.sin(x * 2.3 + plank) + 0.2 * np.sin(x * 9.1)))
    seam = np.abs(y / 0.14 - np.round(y / 0.14)) * 0.14 < 0.0015
    f = tone * (0.82 + 0.22 * grain) * np.where(seam, 0.45, 1.0)
    return _srgb_to_linear((168, 118, 70))[None] * f[:, None]


@dataclass
class _Scene:
    """Triangle meshes in the optical frame with their materials, and the raycasting scene."""

    scene: o3d.t.geometry.RaycastingScene = field(default_factory=o3d.t.geometry.RaycastingScene)
    labels: list[int] = field(default_factory=list)
    rgbs: list[tuple] = field(default_factory=list)
    smooth: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def add(self, verts, tris, label: int, rgb: tuple, normals=None) -> None:
        gid = self.scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(verts, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(tris, dtype=np.uint32)),
        )
        assert gid == len(self.labels)
        self.labels.append(label)
        self.rgbs.append(rgb)
        if normals is not None:
            self.smooth[gid] = (np.asarray(normals, dtype=float), np.asarray(tris))


def _build_scene(x, grip_poses, world_from_optical, lab: ForeignLab, occluder, room: Room) -> _Scene:
    R, t = world_from_optical[:3, :3], world_from_optical[:3, 3]

    def opt(p):  # world points -> optical frame
        return (np.asarray(p, dtype=float) - t) @ R

    sc = _Scene()
    side = np.cross(room.wall_normal, [0.0, 0.0, 1.0])
    centre = room.wall_point + 1.2 * room.wall_normal
    verts, tris = _quad([centre[0] - 3.0, centre[1] - 3.0, room.table_z], [6.0, 0.0, 0.0], [0.0, 6.0, 0.0])
    sc.add(opt(verts), tris, TABLE, (0, 0, 0))  # wood: textured in render_frame
    corner = room.wall_point - 3.0 * side
    corner[2] = room.table_z - 0.1
    verts, tris = _quad(corner, 6.0 * side, [0.0, 0.0, 2.6])
    sc.add(opt(verts), tris, WALL, (158, 158, 152))
    v, n, tr = _tube(_centreline(x), lab.rope_radius_m)
    sc.add(opt(v), tr, ROPE, tuple(lab.rope_rgb), normals=n @ R)
    for pose in grip_poses:
        for bv, bt, rgb in _gripper_boxes(np.asarray(pose, dtype=float), lab):
            sc.add(opt(bv), bt, GRIPPER, rgb)
    if occluder is not None:
        c = np.linspace(occluder.tip, occluder.root, 12)
        v, n, tr = _tube(c, occluder.radius, sides=20)
        sc.add(opt(v), tr, OCCLUDER, tuple(occluder.rgb), normals=n @ R)
    return sc


def _rays(origin: np.ndarray, direction: np.ndarray) -> o3d.core.Tensor:
    o = np.broadcast_to(origin, direction.shape)
    return o3d.core.Tensor(np.ascontiguousarray(np.concatenate([o, direction], axis=-1), dtype=np.float32))


def render_frame(
    x: np.ndarray,
    grip_poses: np.ndarray,
    world_from_optical: np.ndarray,
    lab: ForeignLab,
    rng: np.random.Generator,
    occluder: Occluder | None = None,
    room: Room | None = None,
) -> Frame:
    """One RGB-D frame of the rope x (n, 3) held by grippers at ``grip_poses`` (2, 7) (world), with
    labels. ``room``: the clip's table and wall (default: :func:`make_room` of this frame alone)."""
    x = np.asarray(x, dtype=float)
    room = room if room is not None else make_room(x[None], world_from_optical)
    sc = _build_scene(x, grip_poses, world_from_optical, lab, occluder, room)
    R = world_from_optical[:3, :3]
    H, W = lab.height, lab.width
    d = _pixel_rays(lab)
    hit = sc.scene.cast_rays(_rays(np.zeros(3), d))
    z = hit["t_hit"].numpy().astype(float)  # the ray's z is 1: the hit distance is the depth
    found = np.isfinite(z)
    gid = np.where(found, hit["geometry_ids"].numpy(), 0).astype(np.int64)
    labels = np.asarray(sc.labels)[gid] * found
    P = d * np.where(found, z, 0.0)[..., None]  # optical frame

    # normals (optical frame), smooth on the tube and the arm, turned toward the camera
    n = hit["primitive_normals"].numpy().astype(float)
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    uv = hit["primitive_uvs"].numpy().astype(float)
    for g, (vn, tris) in sc.smooth.items():
        m = found & (gid == g)
        if m.any():
            tri = tris[prim[m]]
            a, b = uv[m, 0:1], uv[m, 1:2]
            n[m] = (1 - a - b) * vn[tri[:, 0]] + a * vn[tri[:, 1]] + b * vn[tri[:, 2]]
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    dn = d / np.linalg.norm(d, axis=-1, keepdims=True)
    cos_cam = -(n * dn).sum(-1)
    n = np.where(cos_cam[..., None] < 0, -n, n)
    cos_cam = np.abs(cos_cam)

    # --- depth: what the projector lights and the stereo pair matches
    B = lab.baseline_m
    proj = np.array([B, 0.0, 0.0])
    valid = found & (z <= lab.max_range_m)
    to_p = P - proj
    dist_p = np.linalg.norm(to_p, axis=-1)
    cos_proj = np.abs((n * to_p).sum(-1)) / np.maximum(dist_p, 1e-12)
    cos_max = math.cos(math.radians(lab.grazing_deg))
    valid &= (cos_cam > cos_max) & (cos_proj > cos_max)
    if B > 0:
        idx = np.flatnonzero(valid)
        shadow = sc.scene.test_occlusions(_rays(proj, to_p.reshape(-1, 3)[idx]), tfar=1.0 - 1e-3).numpy()
        valid.reshape(-1)[idx[shadow]] = False
    valid &= rng.random((H, W)) >= lab.speckle_share
    zn = np.zeros((H, W))
    if B > 0:
        disp = lab.fx * B / z[valid] + rng.normal(0.0, lab.disparity_sigma_px, int(valid.sum()))
        disp = np.round(disp / lab.disparity_step_px) * lab.disparity_step_px
        ok = disp > 0
        zv = np.zeros_like(disp)
        zv[ok] = lab.fx * B / disp[ok]
        zn[valid] = zv
        valid &= zn > 0
    else:
        zn[valid] = z[valid]
    xyz = np.where(valid[..., None], d * zn[..., None], 0.0).astype(np.float32)

    # --- colour: Lambertian + ambient + a small Blinn-Phong highlight, cast shadows, gamma, noise
    albedo = np.zeros((H, W, 3))
    ks = np.zeros((H, W))
    shine = np.full((H, W), 20.0)
    for g, rgb in enumerate(sc.rgbs):
        m = found & (gid == g)
        if not m.any():
            continue
        lab_g = sc.labels[g]
        if lab_g == TABLE:
            albedo[m] = _wood(P[m] @ R.T + world_from_optical[:3, 3])
            ks[m] = 0.05
        else:
            albedo[m] = _srgb_to_linear(rgb)
            ks[m] = {ROPE: 0.12, GRIPPER: 0.45, OCCLUDER: 0.05}.get(lab_g, 0.0)
            shine[m] = {ROPE: 25.0, GRIPPER: 60.0}.get(lab_g, 15.0)
    albedo[~found] = _srgb_to_linear((18, 18, 20))
    back = -room.wall_normal  # horizontal, away from the camera
    L = R.T @ (np.array([0.0, 0.0, 1.0]) - 0.55 * back + 0.25 * np.cross(back, [0.0, 0.0, 1.0]))
    L /= np.linalg.norm(L)
    lit = np.clip((n * L).sum(-1), 0.0, None) * found
    idx = np.flatnonzero(lit > 0)
    if len(idx):
        origins = P.reshape(-1, 3)[idx] + 1e-3 * n.reshape(-1, 3)[idx]
        blocked = sc.scene.test_occlusions(
            o3d.core.Tensor(
                np.concatenate([origins, np.broadcast_to(L, origins.shape)], 1).astype(np.float32)
            )
        ).numpy()
        lit.reshape(-1)[idx[blocked]] = 0.0
    half = L - dn
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    spec = ks * np.clip((n * half).sum(-1), 0.0, None) ** shine * (lit > 0)
    radiance = albedo * (0.32 + 0.75 * lit)[..., None] + spec[..., None]
    enc = 255.0 * np.clip(radiance, 0.0, 1.0) ** (1.0 / lab.gamma)
    enc += rng.normal(0.0, lab.colour_sigma, enc.shape)
    rgb = np.clip(np.round(enc), 0, 255).astype(np.uint8)
    return Frame(xyz, rgb, labels.astype(np.uint8))


def render_cloud(
    x: np.ndarray,
    grip_poses: np.ndarray,
    world_from_optical: np.ndarray,
    lab: ForeignLab,
    rng: np.random.Generator,
    occluder: Occluder | None = None,
    room: Room | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """x (n, 3) the rope's marker positions (world); returns xyz (H, W, 3) float32 in the optical
    frame, missing points as (0, 0, 0) (as RealSense writes them), and rgb (H, W, 3) uint8."""
    f = render_frame(x, grip_poses, world_from_optical, lab, rng, occluder, room)
    return f.xyz, f.rgb


# -------------------------------------------------------------------------------------- the occluder


@dataclass(frozen=True)
class OccluderPlan:
    """An arm in front of the rope during [t_start, t_end) of a clip, drifting slowly."""

    anchor: np.ndarray  # where the arm's axis crosses the occluding plane, at offset 0
    axis: np.ndarray  # unit, from the tip toward the root
    lateral: np.ndarray  # unit, normal to the axis and to the view
    offset: float
    advance: float  # tip = anchor + offset * lateral + advance * axis
    t_start: float
    t_end: float
    length: float = 1.2
    radius: float = 0.04

    def at(self, t: float) -> Occluder | None:
        """The arm at time t [s] of the clip (None outside its half)."""
        if not self.t_start <= t < self.t_end:
            return None
        s = t - 0.5 * (self.t_start + self.t_end)  # the drift is zero in the middle
        off = self.offset + 0.015 * math.sin(2 * math.pi * 0.25 * s)
        adv = self.advance + 0.02 * math.sin(2 * math.pi * 0.17 * s)
        tip = self.anchor + off * self.lateral + adv * self.axis
        return Occluder(tip, tip + self.length * self.axis, self.radius)


def _hidden_share(
    camera: np.ndarray, curves: np.ndarray, tips: np.ndarray, axis, length, radius
) -> np.ndarray:
    """The share (by arc length, averaged over the curves (f, k, 3)) of a rope hidden from the camera by
    arms (cylinders with flat ends) from each of tips (g, 3) along axis, sampled along the lines of
    sight."""
    u = np.linspace(0.05, 0.97, 70)
    share = np.zeros(len(tips))
    for curve in curves:
        w = np.linalg.norm(np.gradient(curve, axis=0), axis=1)
        w /= w.sum()
        q = camera + u[:, None, None] * (curve - camera)[None]  # (70, k, 3)
        rel = q[None] - tips[:, None, None, :]  # (g, 70, k, 3)
        along = rel @ axis
        dist = np.linalg.norm(rel - along[..., None] * axis, axis=-1)
        hidden = ((dist < radius) & (along >= 0.0) & (along <= length)).any(axis=1)  # (g, k)
        share += hidden @ w
    return share / len(curves)


def plan_occluder(
    positions: np.ndarray, dt: float, world_from_optical: np.ndarray, lab: ForeignLab
) -> OccluderPlan:
    """A forearm between the camera and the rope, 55 % of the way to it, for the middle half of the
    clip: placed across the rope where it hides most of it over that half, then drawn back along its
    axis until it hides ``lab.occluded_share`` of it (by length, on average over that half)."""
    positions = np.asarray(positions, dtype=float)
    T = len(positions)
    frames = np.linspace(T // 4, (3 * T) // 4 - 1, 8).round().astype(int)
    curves = np.stack([_centreline(positions[i], 120) for i in frames])
    mid = curves[len(curves) // 2]
    cam = world_from_optical[:3, 3]
    centre = mid[len(mid) // 2]
    view = (centre - cam) / np.linalg.norm(centre - cam)
    chord = positions[T // 2, -1] - positions[T // 2, 0]
    a = chord - np.dot(chord, view) * view
    if np.linalg.norm(a) < 1e-3 * max(np.linalg.norm(chord), 1e-9):  # ends in line of sight
        a = np.cross(view, [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    tilt = math.radians(25.0)
    axis = math.cos(tilt) * a + math.sin(tilt) * np.cross(view, a)
    lateral = np.cross(view, axis)
    anchor = cam + 0.55 * (centre - cam)
    length, radius, full = 1.2, 0.04, -0.6
    offsets = np.linspace(-0.3, 0.3, 61)
    shares = _hidden_share(
        cam, curves, anchor + offsets[:, None] * lateral + full * axis, axis, length, radius
    )
    off = float(offsets[int(np.argmax(shares))])
    lo, hi = full, 0.6  # the hidden share falls from lo to hi
    for _ in range(25):
        m = 0.5 * (lo + hi)
        tip = anchor + off * lateral + m * axis
        s = _hidden_share(cam, curves, tip[None], axis, length, radius)[0]
        lo, hi = (m, hi) if s > lab.occluded_share else (lo, m)
    dur = (T - 1) * dt
    return OccluderPlan(anchor, axis, lateral, off, 0.5 * (lo + hi), 0.25 * dur, 0.75 * dur, length, radius)


# ------------------------------------------------------------------------------------------- the bag


def _stamp(ns: int):
    return TYPESTORE.types["builtin_interfaces/msg/Time"](
        sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000)
    )


def _header(ns: int, frame: str):
    return TYPESTORE.types["std_msgs/msg/Header"](stamp=_stamp(ns), frame_id=frame)


def _tf(ns: int, parent: str, child: str, T: np.ndarray):
    ty = TYPESTORE.types
    q = _quat_of_matrix(T[:3, :3])
    return ty["geometry_msgs/msg/TransformStamped"](
        header=_header(ns, parent),
        child_frame_id=child,
        transform=ty["geometry_msgs/msg/Transform"](
            translation=ty["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=ty["geometry_msgs/msg/Quaternion"](
                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
            ),
        ),
    )


def tf_static_chain(world_from_optical: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    """(parent, child, parent_from_child) of the lab's /tf_static: world -> base_link -> camera_link ->
    camera_color_optical_frame (and camera_depth_optical_frame, 15 mm to the colour camera's right)."""
    link_from_optical = _transform(_matrix_of_quat(LINK_FROM_OPTICAL_Q), (0.0, 0.0, 0.0))
    wb = world_from_base()
    base_from_link = _inverse(wb) @ world_from_optical @ _inverse(link_from_optical)
    link_from_depth = link_from_optical.copy()
    link_from_depth[:3, 3] = (0.0, -0.015, 0.0)
    return [
        (WORLD, BASE, wb),
        (BASE, CAMERA_LINK, base_from_link),
        (CAMERA_LINK, COLOR_OPTICAL, link_from_optical),
        (CAMERA_LINK, DEPTH_OPTICAL, link_from_depth),
    ]


def _camera_info(ns: int, frame: str, width: int, height: int, K: np.ndarray):
    ty = TYPESTORE.types
    P = np.zeros((3, 4))
    P[:, :3] = K
    return ty["sensor_msgs/msg/CameraInfo"](
        header=_header(ns, frame),
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=K.astype(np.float64).ravel(),
        r=np.eye(3).ravel(),
        p=P.ravel(),
        binning_x=0,
        binning_y=0,
        roi=ty["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


CLOUD_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "rgb"],
        "formats": ["<f4", "<f4", "<f4", "<u4"],
        "offsets": [0, 4, 8, 16],
        "itemsize": 20,
    }
)


def _point_cloud(ns: int, xyz: np.ndarray, rgb: np.ndarray):
    """An organized PointCloud2: x y z float32 at 0, 4, 8 and rgb at 16 (0x00RRGGBB read as float32)."""
    ty = TYPESTORE.types
    H, W = xyz.shape[:2]
    pts = np.zeros((H, W), dtype=CLOUD_DTYPE)
    pts["x"], pts["y"], pts["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    c = rgb.astype(np.uint32)
    pts["rgb"] = (c[..., 0] << 16) | (c[..., 1] << 8) | c[..., 2]
    field_ = ty["sensor_msgs/msg/PointField"]
    fields = [
        field_(name=k, offset=o, datatype=7, count=1) for k, o in (("x", 0), ("y", 4), ("z", 8), ("rgb", 16))
    ]
    return ty["sensor_msgs/msg/PointCloud2"](
        header=_header(ns, COLOR_OPTICAL),
        height=H,
        width=W,
        fields=fields,
        is_bigendian=False,
        point_step=20,
        row_step=20 * W,
        data=pts.view(np.uint8).reshape(-1),
        is_dense=False,
    )


def _pose_array(ns: int, poses: np.ndarray):
    ty = TYPESTORE.types
    msgs = [
        ty["geometry_msgs/msg/Pose"](
            position=ty["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=ty["geometry_msgs/msg/Quaternion"](
                x=float(p[3]), y=float(p[4]), z=float(p[5]), w=float(p[6])
            ),
        )
        for p in poses
    ]
    return ty["geometry_msgs/msg/PoseArray"](header=_header(ns, BASE), poses=msgs)


def _qos(durability: QosDurability, reliability: QosReliability, depth: int) -> Qos:
    inf = QosTime(9223372036, 854775807)
    return Qos(
        QosHistory.KEEP_LAST, depth, reliability, durability, inf, inf, QosLiveliness.AUTOMATIC, inf, False
    )


def markers_at(positions: np.ndarray, dt: float, t) -> np.ndarray:
    """The markers (T, n, 3) sampled every dt, linearly interpolated at times t (...) [s]."""
    positions = np.asarray(positions, dtype=float)
    f = np.clip(np.asarray(t, dtype=float) / dt, 0.0, len(positions) - 1)
    i = np.minimum(np.floor(f).astype(int), len(positions) - 2)
    w = (f - i)[..., None, None]
    return (1 - w) * positions[i] + w * positions[i + 1]


def write_clip(
    path: Path,
    positions: np.ndarray,
    dt: float,
    lab: ForeignLab,
    world_from_optical: np.ndarray,
    seed: int,
    occluded: bool,
) -> None:
    """Writes one rosbag2 folder (sqlite3 storage) of the motion positions (T, n, 3) sampled every dt
    seconds (0.01): /tf_static, the robot's TCP poses in base_link at ``pose_hz``, the driver's
    organized clouds and both CameraInfos at ``fps`` (stamp jitter, dropped frames)."""
    path = Path(path)
    positions = np.asarray(positions, dtype=float)
    rng = np.random.default_rng(seed)
    duration = (len(positions) - 1) * dt
    room = make_room(positions, world_from_optical)
    plan = plan_occluder(positions, dt, world_from_optical, lab) if occluded else None

    t_pose = np.arange(math.floor(duration * lab.pose_hz + 1e-9) + 1) / lab.pose_hz
    base_from_world = _inverse(world_from_base())
    refs = roll_references(positions)
    poses_world = gripper_poses(
        markers_at(positions, dt, t_pose), t_pose, lab, markers_at(refs, dt, t_pose)
    )  # (P, 2, 7)
    poses_base = np.empty_like(poses_world)
    for k in range(len(t_pose)):
        for g in range(2):
            poses_base[k, g] = _pose_of(base_from_world @ _matrix_of_pose(poses_world[k, g]))
    pose_ns = START_NS + np.round(t_pose * 1e9).astype(np.int64)

    n_frames = math.floor(duration * lab.fps + 1e-9) + 1
    t_cloud = np.arange(n_frames) / lab.fps + rng.uniform(-lab.stamp_jitter_s, lab.stamp_jitter_s, n_frames)
    t_cloud = np.clip(t_cloud, 0.0, duration)
    kept = t_cloud[rng.random(n_frames) >= lab.drop_share]

    K, Kd = lab.K(), lab.depth_K()
    ser = TYPESTORE.serialize_cdr
    reliable = _qos(QosDurability.VOLATILE, QosReliability.RELIABLE, 10)
    with Writer(path, version=8) as w:
        c_tf = w.add_connection(
            TF_STATIC_TOPIC,
            "tf2_msgs/msg/TFMessage",
            typestore=TYPESTORE,
            offered_qos_profiles=[_qos(QosDurability.TRANSIENT_LOCAL, QosReliability.RELIABLE, 1)],
        )
        c_pose = w.add_connection(
            POSES_TOPIC, "geometry_msgs/msg/PoseArray", typestore=TYPESTORE, offered_qos_profiles=[reliable]
        )
        c_pts = w.add_connection(
            POINTS_TOPIC, "sensor_msgs/msg/PointCloud2", typestore=TYPESTORE, offered_qos_profiles=[reliable]
        )
        c_ci = w.add_connection(
            COLOR_INFO_TOPIC,
            "sensor_msgs/msg/CameraInfo",
            typestore=TYPESTORE,
            offered_qos_profiles=[reliable],
        )
        c_di = w.add_connection(
            DEPTH_INFO_TOPIC,
            "sensor_msgs/msg/CameraInfo",
            typestore=TYPESTORE,
            offered_qos_profiles=[reliable],
        )

        tfs = [_tf(START_NS, a, b, T) for a, b, T in tf_static_chain(world_from_optical)]
        w.write(
            c_tf,
            START_NS,
            ser(TYPESTORE.types["tf2_msgs/msg/TFMessage"](transforms=tfs), "tf2_msgs/msg/TFMessage"),
        )
        k = 0
        for tc in kept:
            ns = START_NS + round(float(tc + lab.stamp_delay_s) * 1e9)
            while k < len(pose_ns) and pose_ns[k] <= ns:
                w.write(
                    c_pose,
                    int(pose_ns[k]),
                    ser(_pose_array(int(pose_ns[k]), poses_base[k]), "geometry_msgs/msg/PoseArray"),
                )
                k += 1
            x = markers_at(positions, dt, tc)
            grips = gripper_poses(x, tc, lab, markers_at(refs, dt, tc))
            occ = plan.at(float(tc)) if plan is not None else None
            xyz, rgb = render_cloud(x, grips, world_from_optical, lab, rng, occ, room)
            w.write(
                c_ci,
                ns,
                ser(_camera_info(ns, COLOR_OPTICAL, lab.width, lab.height, K), "sensor_msgs/msg/CameraInfo"),
            )
            w.write(
                c_di,
                ns,
                ser(
                    _camera_info(ns, DEPTH_OPTICAL, lab.depth_width, lab.depth_height, Kd),
                    "sensor_msgs/msg/CameraInfo",
                ),
            )
            w.write(c_pts, ns, ser(_point_cloud(ns, xyz, rgb), "sensor_msgs/msg/PointCloud2"))
        for j in range(k, len(pose_ns)):
            w.write(
                c_pose,
                int(pose_ns[j]),
                ser(_pose_array(int(pose_ns[j]), poses_base[j]), "geometry_msgs/msg/PoseArray"),
            )


def grippers_of(clips: list[np.ndarray], lab: ForeignLab) -> Grippers:
    """The service's gripper convention for this lab: d0 the TCP's offset, d1 = d0 + the median end
    edge length (markers 0-1, and n-1 - n-2) over the clips."""
    first = np.concatenate([np.linalg.norm(c[:, 1] - c[:, 0], axis=-1) for c in clips])
    last = np.concatenate([np.linalg.norm(c[:, -2] - c[:, -1], axis=-1) for c in clips])
    d0 = lab.tcp_offset_m
    return Grippers(
        first=GripOffsets(d0=d0, d1=d0 + float(np.median(first))),
        last=GripOffsets(d0=d0, d1=d0 + float(np.median(last))),
    )


def _offsets(o: GripOffsets, lab: ForeignLab) -> dict:
    """One gripper's entry of service.yaml; the axis only when it is not the default +x."""
    axis = {"x": None, "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0]}[lab.rope_axis]
    return {"d0": o.d0, "d1": o.d1, **({"axis": axis} if axis else {})}


def write_session(
    out: Path, clips: list[np.ndarray], dt: float, lab: ForeignLab, world_from_optical
) -> tuple[list[Path], Path, Path]:
    """Every clip as a bag folder in out (``clip_000``, ...; every ``occluded_every``-th one with the
    arm), plus ``service.yaml`` (the gripper convention) and ``rope_colour.yaml`` ({"segmentation":
    {"hsv_low": [...], "hsv_high": [...]}}). Returns (bags, service_yaml, colour_yaml)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    world_from_optical = np.asarray(world_from_optical, dtype=float)
    bags = []
    for i, positions in enumerate(clips):
        path = out / f"clip_{i:03d}"
        every = lab.occluded_every
        write_clip(
            path,
            positions,
            dt,
            lab,
            world_from_optical,
            seed=1000 + i,
            occluded=every > 0 and i % every == every - 1,
        )
        bags.append(path)
    g = grippers_of(clips, lab)
    service_yaml = out / "service.yaml"
    service_yaml.write_text(
        yaml.safe_dump(
            {"grippers": {k: _offsets(o, lab) for k, o in (("first", g.first), ("last", g.last))}},
            sort_keys=False,
        )
    )
    colour_yaml = out / "rope_colour.yaml"
    colour_yaml.write_text(
        yaml.safe_dump({"segmentation": {"hsv_low": list(lab.hsv_low), "hsv_high": list(lab.hsv_high)}})
    )
    return bags, service_yaml, colour_yaml
