"""ROS 2 messages as CDR bytes, exactly what zenoh-bridge-ros2dds carries, via the rosbags typestore.

Decoders validate what the loop relies on and raise :class:`InputError` with a short reason, which
becomes the name of a rejection counter.
"""

from __future__ import annotations

import numpy as np
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
T = TYPESTORE.types
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
FLOAT32, FLOAT64, UINT8, UINT32 = (
    T["sensor_msgs/msg/PointField"].FLOAT32,
    T["sensor_msgs/msg/PointField"].FLOAT64,
    T["sensor_msgs/msg/PointField"].UINT8,
    T["sensor_msgs/msg/PointField"].UINT32,
)
_FORMAT = {FLOAT32: "<f4", FLOAT64: "<f8", UINT8: "u1", UINT32: "<u4"}  # PointField type -> numpy


class InputError(ValueError):
    """A message the service refuses; ``reason`` is a stable counter name."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


def encode(msg, typename: str) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(msg, typename))


def decode(raw: bytes, typename: str):
    try:
        return TYPESTORE.deserialize_cdr(raw, typename)
    except Exception as exc:  # rosbags raises several types on garbage; all mean the same here
        raise InputError("malformed_cdr", f"{typename}: {type(exc).__name__}") from None


def definition(typename: str) -> str:
    """The ros2msg schema text (with dependencies) that MCAP files and Foxglove expect."""
    return TYPESTORE.generate_msgdef(typename, ros_version=2)[0]


# ----- time -----------------------------------------------------------------------------------
def header(stamp_ns: int, frame_id: str):
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
    )


def stamp_ns(hdr) -> int:
    return int(hdr.stamp.sec) * 1_000_000_000 + int(hdr.stamp.nanosec)


# ----- poses ----------------------------------------------------------------------------------
def _pose(p) -> object:
    P = T["geometry_msgs/msg/Pose"]
    return P(
        position=T["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=T["geometry_msgs/msg/Quaternion"](
            x=float(p[3]), y=float(p[4]), z=float(p[5]), w=float(p[6])
        ),
    )


def _pose_vec(p) -> list[float]:
    return [
        p.position.x,
        p.position.y,
        p.position.z,
        p.orientation.x,
        p.orientation.y,
        p.orientation.z,
        p.orientation.w,
    ]


def _check_poses(poses: np.ndarray) -> np.ndarray:
    if not np.all(np.isfinite(poses)):
        raise InputError("nan_pose")
    qn = np.linalg.norm(poses[:, 3:], axis=1)
    if np.any(np.abs(qn - 1.0) > 0.1):
        raise InputError("bad_quaternion", f"norms {np.round(qn, 3).tolist()}")
    poses = poses.copy()
    poses[:, 3:] /= qn[:, None]
    return poses


def pose_array(stamp: int, poses, frame_id: str = "world") -> bytes:
    """``poses`` (k, 7): x y z qx qy qz qw."""
    msg = T[POSE_ARRAY](
        header=header(stamp, frame_id), poses=[_pose(p) for p in np.asarray(poses, dtype=float)]
    )
    return encode(msg, POSE_ARRAY)


def check_frame(hdr, frame_id: str | None) -> None:
    """Refuse a message stamped in another frame than ``frame_id`` (an empty frame_id is taken as it)."""
    if frame_id is not None and hdr.frame_id not in ("", frame_id):
        raise InputError("wrong_frame", f"frame_id {hdr.frame_id!r}, expected {frame_id!r}")


def parse_pose_array(raw: bytes, expected: int = 2, frame_id: str | None = None) -> tuple[int, np.ndarray]:
    msg = decode(raw, POSE_ARRAY)
    check_frame(msg.header, frame_id)
    if len(msg.poses) != expected:
        raise InputError("wrong_pose_count", f"{len(msg.poses)} poses, expected {expected}")
    return stamp_ns(msg.header), _check_poses(np.array([_pose_vec(p) for p in msg.poses], dtype=float))


def pose_stamped(stamp: int, pose, frame_id: str = "world") -> bytes:
    return encode(T[POSE_STAMPED](header=header(stamp, frame_id), pose=_pose(pose)), POSE_STAMPED)


def parse_pose_stamped(raw: bytes, frame_id: str | None = None) -> tuple[int, np.ndarray]:
    msg = decode(raw, POSE_STAMPED)
    check_frame(msg.header, frame_id)
    return stamp_ns(msg.header), _check_poses(np.array([_pose_vec(msg.pose)], dtype=float))[0]


# ----- camera info ----------------------------------------------------------------------------
# ROS (and OpenCV) put pixel (u, v)'s centre at the integers u, v; perception's Camera puts pixel j's
# centre at j + 1/2 (its rays and projections). The principal point moves by half a pixel between the two.
PIXEL_CENTRE = 0.5


def camera_info(stamp: int, K, width: int, height: int, frame_id: str = "camera") -> bytes:
    """CameraInfo of perception's intrinsics ``K`` (pixel centres at j + 1/2), written in ROS's
    convention (pixel centres at the integers: cx and cy half a pixel smaller)."""
    K = np.asarray(K, dtype=float).reshape(9).copy()
    K[[2, 5]] -= PIXEL_CENTRE
    P = np.zeros(12)
    P[[0, 1, 2, 4, 5, 6, 10]] = K[[0, 1, 2, 3, 4, 5, 8]]
    msg = T[CAMERA_INFO](
        header=header(stamp, frame_id),
        height=int(height),
        width=int(width),
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=K,
        r=np.eye(3).reshape(9),
        p=P,
        binning_x=0,
        binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    return encode(msg, CAMERA_INFO)


def parse_camera_info(raw: bytes) -> tuple[int, np.ndarray, int, int]:
    """``(stamp, K, width, height)`` with ``K`` in perception's convention (pixel centres at j + 1/2:
    ROS's cx and cy plus half a pixel)."""
    msg = decode(raw, CAMERA_INFO)
    K = np.asarray(msg.k, dtype=float).reshape(3, 3).copy()
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or msg.width == 0 or msg.height == 0:
        raise InputError("bad_camera_info")
    K[0, 2] += PIXEL_CENTRE
    K[1, 2] += PIXEL_CENTRE
    return stamp_ns(msg.header), K, int(msg.width), int(msg.height)


# ----- point clouds ---------------------------------------------------------------------------
def _pack_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = rgb.astype(np.uint32)
    return ((rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]).astype(np.uint32)


def point_cloud(stamp: int, xyz: np.ndarray, rgb: np.ndarray, frame_id: str = "camera") -> bytes:
    """Organized cloud: ``xyz`` (H, W, 3) float32 (NaN where nothing was seen), ``rgb`` (H, W, 3) uint8;
    rgb is packed into a float32 field as ROS drivers do."""
    H, W = xyz.shape[:2]
    rec = np.zeros((H, W), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    rec["rgb"] = _pack_rgb(rgb)
    PF = T["sensor_msgs/msg/PointField"]
    fields = [
        PF(name=n, offset=4 * i, datatype=FLOAT32, count=1) for i, n in enumerate(("x", "y", "z", "rgb"))
    ]
    msg = T[POINT_CLOUD2](
        header=header(stamp, frame_id),
        height=H,
        width=W,
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * W,
        data=np.frombuffer(rec.tobytes(), dtype=np.uint8),
        is_dense=False,
    )
    return encode(msg, POINT_CLOUD2)


def _structured(msg, wanted: dict[str, tuple[int, ...]]) -> np.ndarray:
    """The cloud's data viewed as a (H*W,) record array of the wanted fields; checks the layout."""
    if msg.is_bigendian:
        raise InputError("wrong_point_fields", "big-endian data")
    fields = {f.name: f for f in msg.fields}
    names, formats, offsets = [], [], []
    for name, types in wanted.items():
        f = fields.get(name)
        if f is None or f.datatype not in types or f.count != 1:
            raise InputError("wrong_point_fields", f"field {name!r} missing or not {types}")
        names.append(name)
        formats.append(_FORMAT[f.datatype])
        offsets.append(f.offset)
    step, H, W = int(msg.point_step), int(msg.height), int(msg.width)
    if (
        step <= 0
        or any(o + np.dtype(f).itemsize > step for o, f in zip(offsets, formats))
        or msg.row_step < step * W
        or len(msg.data) != msg.row_step * H
    ):
        raise InputError("wrong_point_fields", "inconsistent sizes")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    data = np.asarray(msg.data, dtype=np.uint8).reshape(H, msg.row_step)[:, : step * W]
    return np.ascontiguousarray(data).view(dtype).reshape(H * W)


def _channel(values: np.ndarray) -> np.ndarray:
    """One colour channel as uint8: uint8 as it is, float in 0..1 scaled (0..255 when it passes 1)."""
    if values.dtype == np.uint8:
        return values
    v = np.nan_to_num(values.astype(np.float64))
    scale = 255.0 if v.max(initial=0.0) <= 1.0 else 1.0
    return np.clip(np.rint(v * scale), 0, 255).astype(np.uint8)


def parse_point_cloud(raw: bytes) -> tuple[int, np.ndarray, np.ndarray, str]:
    """-> stamp, xyz (H, W, 3) float32 (NaN where nothing was seen), rgb (H, W, 3) uint8, frame_id.
    The cloud stays organized: the tracker reasons about occlusion on the image grid. An unorganized
    cloud (height 1: RealSense's pointcloud filter, ``create_cloud``) comes as (1, N, 3); the
    estimator puts it on its camera's grid (``perception.organize_cloud``).

    x, y, z may be float32 or float64. Drivers mark a pixel without depth as NaN, as ``(0, 0, 0)``
    (RealSense's ordered clouds) or as +-inf; all become NaN here, before a cloud published in the
    world frame is moved into the camera's, where its zeros would turn into a wall of points."""
    msg = decode(raw, POINT_CLOUD2)
    if msg.height < 1 or msg.width < 1:
        raise InputError("empty_cloud", f"{msg.width}x{msg.height}")
    # colour as "rgb" (most drivers) or "rgba" (PCL's PointXYZRGBA, some structured-light cameras),
    # both packing red, green, blue in the low three bytes, or as three fields "r", "g", "b" (uint8,
    # or float in 0..1 as Open3D's colours), as clouds made in Python often are
    names = {f.name for f in msg.fields}
    colour = "rgba" if "rgba" in names and "rgb" not in names else "rgb"
    separate = colour not in names and {"r", "g", "b"} <= names
    xyz_types = (FLOAT32, FLOAT64)
    wanted = {"x": xyz_types, "y": xyz_types, "z": xyz_types}
    if separate:
        wanted.update({c: (UINT8, FLOAT32, FLOAT64) for c in "rgb"})
    else:
        wanted[colour] = (FLOAT32, UINT32)
    rec = _structured(msg, wanted)
    H, W = int(msg.height), int(msg.width)
    with np.errstate(invalid="ignore", over="ignore"):
        x, y, z = (rec[c].astype(np.float32) for c in "xyz")
        missing = ~np.isfinite(x + y + z) | ((z == 0) & (x == 0) & (y == 0))
    xyz = np.stack([np.where(missing, np.float32(np.nan), c) for c in (x, y, z)], axis=1).reshape(H, W, 3)
    if separate:
        rgb = np.stack([_channel(rec[c]) for c in "rgb"], axis=1).reshape(H, W, 3)
    else:
        packed = rec[colour].view(np.uint32) if rec[colour].dtype == np.float32 else rec[colour]
        rgb = (
            np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1)
            .astype(np.uint8)
            .reshape(H, W, 3)
        )
    if not np.isfinite(xyz).any():
        raise InputError("empty_cloud")
    return stamp_ns(msg.header), xyz, rgb, msg.header.frame_id


def vertices_cloud(stamp: int, x: np.ndarray, observed: np.ndarray, frame_id: str = "world") -> bytes:
    """The estimate: one point per vertex, fields x, y, z (float32) and observed (uint8)."""
    n = len(x)
    rec = np.zeros(
        n,
        dtype=np.dtype(
            {
                "names": ["x", "y", "z", "observed"],
                "formats": ["<f4", "<f4", "<f4", "u1"],
                "offsets": [0, 4, 8, 12],
                "itemsize": 16,
            }
        ),
    )
    rec["x"], rec["y"], rec["z"] = x[:, 0], x[:, 1], x[:, 2]
    rec["observed"] = np.asarray(observed, dtype=np.uint8)
    PF = T["sensor_msgs/msg/PointField"]
    fields = [PF(name=n_, offset=4 * i, datatype=FLOAT32, count=1) for i, n_ in enumerate(("x", "y", "z"))]
    fields.append(PF(name="observed", offset=12, datatype=UINT8, count=1))
    msg = T[POINT_CLOUD2](
        header=header(stamp, frame_id),
        height=1,
        width=n,
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * n,
        data=np.frombuffer(rec.tobytes(), dtype=np.uint8),
        is_dense=True,
    )
    return encode(msg, POINT_CLOUD2)


def parse_vertices(raw: bytes) -> tuple[int, np.ndarray, np.ndarray]:
    """Client side of ``{ns}/vertices``: -> stamp, x (n, 3) float32, observed (n,) bool."""
    msg = decode(raw, POINT_CLOUD2)
    rec = _structured(msg, {"x": (FLOAT32,), "y": (FLOAT32,), "z": (FLOAT32,), "observed": (UINT8,)})
    return (
        stamp_ns(msg.header),
        np.stack([rec["x"], rec["y"], rec["z"]], axis=1),
        rec["observed"].astype(bool),
    )


MARKER = "visualization_msgs/msg/Marker"


def shape_marker(stamp: int, x: np.ndarray, frame_id: str = "world", ns: str = "deform") -> bytes:
    """The estimate as a line RViz and Foxglove draw as they are: a ``Marker`` LINE_STRIP through
    the vertices (1 cm wide, orange, no lifetime), id 0 in namespace ``ns``."""
    Mk = T[MARKER]
    P = T["geometry_msgs/msg/Point"]
    msg = Mk(
        header=header(stamp, frame_id),
        ns=ns,
        id=0,
        type=Mk.LINE_STRIP,
        action=Mk.ADD,
        pose=_pose((0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)),
        scale=T["geometry_msgs/msg/Vector3"](x=0.01, y=0.0, z=0.0),
        color=T["std_msgs/msg/ColorRGBA"](r=1.0, g=0.5, b=0.0, a=1.0),
        lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=False,
        points=[P(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in np.asarray(x, dtype=float)],
        colors=[],
        texture_resource="",
        texture=T["sensor_msgs/msg/CompressedImage"](
            header=header(0, ""), format="", data=np.zeros(0, dtype=np.uint8)
        ),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, dtype=np.uint8)),
        mesh_use_embedded_materials=False,
    )
    return encode(msg, MARKER)


def parse_shape_marker(raw: bytes) -> tuple[int, np.ndarray]:
    """Client side of ``{ns}/shape``: -> stamp, points (n, 3) float64."""
    msg = decode(raw, MARKER)
    return stamp_ns(msg.header), np.array([[p.x, p.y, p.z] for p in msg.points], dtype=float).reshape(-1, 3)
