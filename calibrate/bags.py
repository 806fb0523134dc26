"""Calibration input: rosbag2 folders or MCAP files -> :class:`Clip` (gripper poses, RGB-D clouds,
the camera), decoded with the service's own message codecs so that a bag means to calibration what
it means to the running service.

Topics are found by message type when that is unambiguous (one ``PoseArray``, one ``PointCloud2``
with colour, organized preferred, one ``CameraInfo``), chosen with :class:`Topics` otherwise. An
unorganized cloud (height 1: RealSense's pointcloud filter) is put on the image grid of its
CameraInfo, as the service does. The camera's pose (its
optical frame in the world frame) comes, in this order, from a chosen topic,
from ``/tf_static`` (the chain from the world frame to the clouds' frame, or CameraInfo's), from a lone
``PoseStamped`` topic, or from the config. Times are the messages' header stamps, never the bag's
receive times: clouds and poses arrive over different paths with different delays.

Clouds are large (1-5 MB each, 150 per 5 s clip), so a clip keeps only where they are; they are
decoded one at a time by :meth:`Clip.clouds`.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader

from calibrate.errors import CalibrationError
from perception import Camera, organize_cloud
from service import messages as M
from service.config import ServiceConfig
from service.geometry import matrix_to_pose, pose_matrix
from service.tracking import camera_frame_cloud, cloud_intrinsics

TF_MESSAGE = "tf2_msgs/msg/TFMessage"


@dataclass(frozen=True)
class Topics:
    """Topics chosen by the user (None: found by message type)."""

    poses: str | None = None
    points: str | None = None
    camera_info: str | None = None
    camera_pose: str | None = None  # a PoseStamped or a TFMessage topic


@dataclass(frozen=True)
class Clip:
    """One bag: gripper poses with their stamps, where its clouds are, and the camera.

    ``poses`` (P, 2, 7): x y z qx qy qz qw of the first and last gripper, world frame, at
    ``pose_stamps_ns`` (P,) increasing. ``camera``: intrinsics and ``world_from_camera`` (optical
    frame). ``camera_source``: where the pose came from (``tf_static``, a topic, ``config``).
    ``world_frame``: the frame of both (:func:`read_clip`), ``poses_from``: how the poses got there."""

    name: str
    path: Path
    pose_stamps_ns: np.ndarray
    poses: np.ndarray
    points_topic: str
    n_clouds: int
    camera: Camera
    camera_source: str
    world_frame: str
    poses_from: str = ""  # the poses' frame and how it became the world frame
    intrinsics_from: str = ""  # the CameraInfo topic, or the clouds themselves and why
    cloud_delay_ns: int = 0  # how late the clouds are stamped against the poses (calibrate.latency)

    @property
    def duration_s(self) -> float:
        return float(self.pose_stamps_ns[-1] - self.pose_stamps_ns[0]) / 1e9

    def clouds(self) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """Decoded clouds in stamp order: ``(stamp_ns, xyz (H, W, 3) float32 camera frame, rgb (H, W,
        3) uint8)``, the stamp less ``cloud_delay_ns`` (the time the cloud was taken, on the poses'
        clock). Clouds the service would refuse (malformed, empty, wrong size) are skipped; a
        cloud published in the world frame is moved back into the optical frame, and an unorganized
        one put on the camera's image grid, as the service does."""
        cam = self.camera
        out = []
        with _open(self.path) as reader:
            conns = [c for c in reader.connections if c.topic == self.points_topic]
            for _, _, raw in reader.messages(connections=conns):
                try:
                    stamp, xyz, rgb, frame = M.parse_point_cloud(bytes(raw))
                except M.InputError:
                    continue
                flat = xyz.shape[0] == 1
                if not flat and xyz.shape[:2] != (cam.height, cam.width):
                    continue
                xyz = camera_frame_cloud(xyz, frame, self.world_frame, cam.world_from_camera)
                if flat:
                    xyz, rgb = organize_cloud(xyz, rgb, cam)
                out.append((stamp - self.cloud_delay_ns, xyz, rgb))
                if len(out) > 8:  # a little look-ahead sorts clouds recorded slightly out of order
                    out.sort(key=lambda c: c[0])
                    yield out.pop(0)
        yield from sorted(out, key=lambda c: c[0])


@contextmanager
def _open(path: Path) -> Iterator[AnyReader]:
    """The bag open for reading; a :class:`CalibrationError` naming it when it is no bag."""
    reader = AnyReader([path], default_typestore=M.TYPESTORE)
    try:
        reader.open()
    except Exception as exc:  # rosbags raises several types for what is not a bag
        raise CalibrationError(
            f"{path}: not a readable rosbag2 folder or MCAP file ({type(exc).__name__}: {exc})".replace(
                "\n", " "
            )
        ) from None
    try:
        yield reader
    finally:
        reader.close()


def _pick(path: Path, reader, msgtype: str, chosen: str | None, option: str, what: str, keep=()):
    """The one connection of ``msgtype`` (or the ``chosen`` topic); None when the bag has none. Among
    several, the first of the ``keep`` filters that leaves any narrows them down."""
    if chosen is not None:
        conns = [c for c in reader.connections if c.topic == chosen]
        if not conns:
            topics = ", ".join(sorted({c.topic for c in reader.connections}))
            raise CalibrationError(f"{path}: no topic {chosen} ({option}); the bag has {topics}")
        return conns[0]
    conns = [c for c in reader.connections if c.msgtype == msgtype and c.msgcount > 0]  # recorded, never sent
    for k in keep if len(conns) > 1 else ():
        kept = [c for c in conns if k(c)]
        if kept:
            conns = kept
            break
    if len({c.topic for c in conns}) > 1:
        names = ", ".join(sorted({c.topic for c in conns}))
        raise CalibrationError(f"{path}: several {what} topics ({names}): choose one with {option}")
    return conns[0] if conns else None


def _first(reader, conn):
    for _, _, raw in reader.messages(connections=[conn]):
        return bytes(raw)
    return None


def _camera_info_values(reader, conn) -> tuple | None:
    """A CameraInfo topic's intrinsics, image size and frame (of its first message); None if unusable."""
    raw = _first(reader, conn)
    if raw is None:
        return None
    try:
        _, K, width, height = M.parse_camera_info(raw)
        return (tuple(np.round(K, 6).ravel()), width, height, M.decode(raw, M.CAMERA_INFO).header.frame_id)
    except M.InputError:
        return None


def _first_cloud(reader, conn) -> tuple[object | None, str | None]:
    """The first message of a cloud topic, decoded (None when there is none or it cannot be read),
    and, for an unorganized one, why the service would refuse it as a camera's cloud (None: it
    would not; an organized cloud is not read further here)."""
    raw = _first(reader, conn)
    if raw is None:
        return None, None
    try:
        msg = M.decode(raw, M.POINT_CLOUD2)
    except M.InputError as exc:
        return None, str(exc)
    if msg.height > 1:
        return msg, None
    try:
        M.parse_point_cloud(raw)
    except M.InputError as exc:
        return msg, str(exc)
    return msg, None


def _pick_camera_info(path: Path, reader, chosen: str | None, cloud):
    """The CameraInfo topic of the cloud's image: the ``chosen`` one, the only one, or among several
    (a driver publishes its colour, depth and aligned-depth intrinsics side by side) those of the
    organized ``cloud``'s size (its topic's first message), or for an unorganized cloud those of its
    frame, when they all say the same (one camera's intrinsics published twice)."""
    conns = [c for c in reader.connections if c.msgtype == M.CAMERA_INFO and c.msgcount > 0]
    if chosen is not None or len({c.topic for c in conns}) <= 1:
        return _pick(path, reader, M.CAMERA_INFO, chosen, "--topic-camera-info", "camera info")
    values = {c.topic: _camera_info_values(reader, c) for c in conns}

    def fits(v) -> bool:
        if cloud is None:
            return False
        if cloud.height > 1:
            return v[1:3] == (cloud.width, cloud.height)
        return v[3].strip("/") == cloud.header.frame_id.strip("/")

    fitting = [c for c in conns if values[c.topic] is not None and fits(values[c.topic])]
    if fitting and len({values[c.topic] for c in fitting}) == 1:
        return fitting[0]
    names = ", ".join(sorted({c.topic for c in conns}))
    whose = "the clouds' size" if cloud is None or cloud.height > 1 else "the clouds' frame"
    why = "" if fitting else f", none of them of {whose}"
    raise CalibrationError(
        f"{path}: several camera info topics ({names}){why}: choose one with --topic-camera-info"
    )


def _intrinsics_of_cloud(path, reader, conn, world_from_camera, world: str, why_not: str):
    """``(K, (width, height), source)`` fitted to the clouds themselves (the service's
    :func:`service.tracking.cloud_intrinsics`, so that both read a cloud alike)
    when no camera info is of their image: a driver's colour intrinsics beside clouds registered to
    the depth image, a cloud filter that halved the image, no CameraInfo recorded."""
    for _, _, raw in reader.messages(connections=[conn]):
        try:
            _, xyz, _, frame = M.parse_point_cloud(bytes(raw))
        except M.InputError:
            continue
        K = cloud_intrinsics(camera_frame_cloud(xyz, frame, world, world_from_camera))
        H, W = xyz.shape[:2]
        if K is None:
            raise CalibrationError(
                f"{path}: no camera intrinsics for the clouds' {W}x{H} image ({why_not}), and the clouds "
                "are not one pinhole camera's: record the camera's CameraInfo or choose it with "
                "--topic-camera-info"
            )
        return K, (W, H), f"the {W}x{H} clouds themselves ({why_not})"
    raise CalibrationError(f"{path}: no readable clouds on {conn.topic}")


def _organized(reader, conn) -> bool:
    """A camera's organized cloud (height > 1); the service's own ``vertices`` output is not."""
    raw = _first(reader, conn)
    try:
        return raw is not None and M.decode(raw, M.POINT_CLOUD2).height > 1
    except M.InputError:
        return False


def _coloured(reader, conn) -> bool:
    """A cloud with colour (an unorganized camera cloud; the service's ``vertices`` output has none)."""
    raw = _first(reader, conn)
    try:
        names = {f.name for f in M.decode(raw, M.POINT_CLOUD2).fields} if raw is not None else set()
    except M.InputError:
        return False
    return bool(names & {"rgb", "rgba"}) or {"r", "g", "b"} <= names


def _tf_graph(reader, conns) -> dict[str, list[tuple[str, np.ndarray]]]:
    """Frames and the transforms between them (both ways) from TFMessage connections."""
    graph: dict[str, list[tuple[str, np.ndarray]]] = {}
    for conn in conns:
        for _, _, raw in reader.messages(connections=[conn]):
            for t in reader.deserialize(raw, conn.msgtype).transforms:
                tr, q = t.transform.translation, t.transform.rotation
                T = pose_matrix(np.array([tr.x, tr.y, tr.z, q.x, q.y, q.z, q.w], dtype=float))
                parent, child = t.header.frame_id.strip("/"), t.child_frame_id.strip("/")
                graph.setdefault(parent, []).append((child, T))  # parent_from_child
                graph.setdefault(child, []).append((parent, np.linalg.inv(T)))
    return graph


def _tf_static(reader) -> list:
    return [c for c in reader.connections if c.msgtype == TF_MESSAGE and c.topic == "/tf_static"]


def _world_of_poses(reader, poses_c, tf, world: str) -> tuple[str, str, np.ndarray | None, str]:
    """The world frame, the poses' frame, ``world_from_poses`` (None: the poses are in the world
    frame) and a line saying how.

    The poses are meant in the config's world frame (``world``). A robot may publish them in its
    own (``base_link``): when ``/tf_static`` links the two, the poses are moved into ``world``;
    when nothing links them, the poses' frame is the world (the camera is then looked up from it,
    and gravity taken along its -z, as for any world frame)."""
    raw = _first(reader, poses_c)
    try:
        frame = M.decode(raw, M.POSE_ARRAY).header.frame_id.strip("/") if raw is not None else ""
    except M.InputError:
        frame = ""
    if frame in ("", world):
        return world, world, None, world or "(no frame)"
    T = _world_from(_tf_graph(reader, tf), world, frame) if tf else None
    if T is not None:
        return world, frame, T, f"{frame}, moved into {world} by /tf_static"
    return (
        frame,
        frame,
        None,
        (
            f"{frame} (the config's world frame {world!r} is not linked to it: {frame} is the world; "
            f"serve this rope with frame_id: {frame})"
        ),
    )


def _world_from(graph, world: str, frame: str) -> np.ndarray | None:
    """``world_from_frame`` through the transform graph (breadth first), None if unconnected."""
    seen = {world: np.eye(4)}
    queue = deque([world])
    while queue:
        a = queue.popleft()
        for b, a_from_b in graph.get(a, []):
            if b not in seen:
                seen[b] = seen[a] @ a_from_b
                queue.append(b)
    return seen.get(frame.strip("/"))


def _camera_pose(
    path, reader, topics: Topics, frames: list[str], cfg: ServiceConfig, world: str
) -> tuple[np.ndarray, str]:
    """(4, 4) world_from_camera and where it came from. ``frames``: the frames to look the camera up
    by in a transform tree, in order (the clouds' own frame, then CameraInfo's)."""
    chosen = None
    if topics.camera_pose is not None:
        chosen = _pick(path, reader, "", topics.camera_pose, "--topic-camera-pose", "camera pose")
    tf = [chosen] if chosen is not None and chosen.msgtype == TF_MESSAGE else _tf_static(reader)
    if chosen is None or chosen.msgtype == TF_MESSAGE:
        if tf:
            graph = _tf_graph(reader, tf)
            for frame in frames:
                T = _world_from(graph, world, frame)
                if T is not None:
                    return T, f"{tf[0].topic} ({world} -> {frame})"
            if chosen is not None:
                raise CalibrationError(
                    f"{path}: {chosen.topic} has no transform chain {world} -> {' or '.join(frames)}"
                )
        stamped = [c for c in reader.connections if c.msgtype == M.POSE_STAMPED]
        if len({c.topic for c in stamped}) == 1:
            chosen = stamped[0]
    if chosen is not None:
        if chosen.msgtype != M.POSE_STAMPED:
            raise CalibrationError(
                f"{path}: {chosen.topic} is a {chosen.msgtype}, not a PoseStamped or TFMessage camera pose"
            )
        try:
            _, pose = M.parse_pose_stamped(_first(reader, chosen), frame_id=world)
        except M.InputError as exc:
            raise CalibrationError(f"{path}: camera pose on {chosen.topic}: {exc}") from None
        return pose_matrix(pose), chosen.topic
    return pose_matrix(np.asarray(cfg.camera.pose, dtype=float)), "config (camera.pose)"


def read_clip(path: str | Path, cfg: ServiceConfig, topics: Topics | None = None) -> Clip:
    """One bag as a :class:`Clip`.

    Args:
        path: a rosbag2 folder or an ``.mcap`` file.
        cfg: the service config: the world frame (``frame_id``) and the fallback camera pose.
        topics: topics chosen by the user (default: found by type).

    Returns:
        The clip (clouds are read later, by :meth:`Clip.clouds`).

    Raises:
        CalibrationError: not a bag, no gripper poses, no clouds, no camera info for unorganized
            clouds (their grid is its), an ambiguous or missing topic; every pose refused (the
            reasons counted).
    """
    path = Path(path)
    topics = topics or Topics()
    if not path.exists():
        raise CalibrationError(f"{path}: no such file or folder")
    with _open(path) as reader:
        poses_c = _pick(path, reader, M.POSE_ARRAY, topics.poses, "--topic-poses", "gripper pose")
        if poses_c is None:
            raise CalibrationError(f"{path}: no gripper poses (no {M.POSE_ARRAY} topic)")
        points_c = _pick(
            path,
            reader,
            M.POINT_CLOUD2,
            topics.points,
            "--topic-points",
            "point cloud",
            keep=(lambda c: _organized(reader, c), lambda c: _coloured(reader, c)),
        )
        if points_c is None or points_c.msgcount == 0:
            raise CalibrationError(f"{path}: no clouds (no {M.POINT_CLOUD2} messages)")
        cloud, refused = _first_cloud(reader, points_c)  # read once: 1-5 MB
        if refused is not None and cloud is not None:
            raise CalibrationError(
                f"{path}: the clouds on {points_c.topic} are no camera's clouds ({refused})"
            )
        flat = cloud is not None and cloud.height <= 1  # unorganized: the grid is CameraInfo's
        size = (cloud.width, cloud.height) if cloud is not None and not flat else None
        why_not = f"no {M.CAMERA_INFO} topic"
        try:
            info_c = _pick_camera_info(path, reader, topics.camera_info, cloud)
        except CalibrationError as exc:
            if topics.camera_info is not None:
                raise
            info_c, why_not = None, str(exc).removeprefix(f"{path}: ")  # (a path may hold ": ")
        K, info_frame, intrinsics_from = None, "", ""
        if info_c is not None:
            raw_info = _first(reader, info_c)
            try:
                _, K, width, height = M.parse_camera_info(raw_info)
                info_frame = M.decode(raw_info, M.CAMERA_INFO).header.frame_id
            except M.InputError as exc:
                raise CalibrationError(f"{path}: camera info on {info_c.topic}: {exc}") from None
            intrinsics_from, why_not = info_c.topic, f"{info_c.topic} is of a {width}x{height} image"
            if size is not None and (width, height) != size:
                K = None
        # the points are in their cloud's frame: that one first (a driver may stamp its intrinsics
        # with another frame of the same camera), CameraInfo's when the tree does not have it
        cloud_frame = cloud.header.frame_id.strip("/") if cloud is not None else ""
        frames = [f for f in dict.fromkeys((cloud_frame, info_frame)) if f]
        world, pose_frame, world_from_poses, poses_from = _world_of_poses(
            reader, poses_c, _tf_static(reader), cfg.frame_id
        )
        world_from_camera, source = _camera_pose(path, reader, topics, frames, cfg, world)
        if K is None and flat:
            raise CalibrationError(
                f"{path}: the clouds on {points_c.topic} are unorganized (height 1), and their image grid "
                f"needs the camera's CameraInfo ({why_not}): record it or choose it with --topic-camera-info"
            )
        if K is None:
            K, (width, height), intrinsics_from = _intrinsics_of_cloud(
                path, reader, points_c, world_from_camera, world, why_not
            )
        stamps, poses, refused = [], [], {}
        for _, _, raw in reader.messages(connections=[poses_c]):
            try:
                stamp, p = M.parse_pose_array(bytes(raw), frame_id=pose_frame)
            except M.InputError as exc:
                refused[exc.reason] = refused.get(exc.reason, 0) + 1
                continue  # the service refuses it too
            if world_from_poses is not None:
                p = np.array([matrix_to_pose(world_from_poses @ pose_matrix(q)) for q in p])
            stamps.append(stamp)
            poses.append(p)
    if len(stamps) < 2:
        why = ", ".join(f"{n} {r}" for r, n in sorted(refused.items()))
        raise CalibrationError(
            f"{path}: no gripper poses ({poses_c.topic} has {len(stamps)} usable"
            + (f"; refused: {why})" if why else ")")
        )
    order = np.argsort(stamps, kind="stable")
    stamps_a = np.asarray(stamps, dtype=np.int64)[order]
    keep = np.concatenate([[True], np.diff(stamps_a) > 0])  # one pose per stamp
    camera = Camera(
        float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height, world_from_camera
    )
    return Clip(
        name=path.stem if path.is_file() else path.name,
        path=path,
        pose_stamps_ns=stamps_a[keep],
        poses=np.asarray(poses)[order][keep],
        points_topic=points_c.topic,
        n_clouds=int(points_c.msgcount),
        camera=camera,
        camera_source=source,
        world_frame=world,
        poses_from=poses_from,
        intrinsics_from=intrinsics_from,
    )
