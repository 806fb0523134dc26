"""A clip as a lab records it with ``ros2 bag record``, not as this project writes one: a rosbag2
folder (MCAP or SQLite storage), a camera driver's topic names and optical frame, the camera's pose
only on ``/tf_static`` through the camera's link frame, clouds at 15 Hz on their own clock between
the pose ticks, and a blue rope found through a colour range in a settings file."""

import colorsys
from dataclasses import replace

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import StoragePlugin, Writer

from calibrate.bags import Topics, read_clip
from calibrate.errors import CalibrationError
from calibrate.tracks import track_clip
from deform import generate_recording, generic_model
from perception import load_config, render_recording
from perception.config import RenderConfig
from service import messages as M
from service.config import ServiceConfig
from service.geometry import matrix_to_pose, pose_matrix, poses_from_vertices
from service.scenario import offsets_for

from .conftest import LENGTH, MASS, N

T0_NS = 1_750_000_000_000_000_000
CLOUD_PHASE_MS = 3  # the first cloud 3 ms after the first pose: the two clocks never line up
CLOUD_FPS = 15.0
BLUE = (35, 80, 215)
OPTICAL = "camera_color_optical_frame"
TOPICS = {
    "poses": "/robot/gripper_poses",
    "points": "/camera/camera/depth/color/points",
    "info": "/camera/camera/color/camera_info",
}
# a camera driver's optical frame in its link frame: optical z (forward) along link x, optical x
# (right) along -link y, optical y (down) along -link z; the colour sensor 15 mm beside the link
LINK_FROM_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.015], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def _transform(stamp_ns: int, parent: str, child: str, parent_from_child: np.ndarray):
    T = M.T
    p = matrix_to_pose(parent_from_child)
    return T["geometry_msgs/msg/TransformStamped"](
        header=M.header(stamp_ns, parent),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=p[3], y=p[4], z=p[5], w=p[6]),
        ),
    )


def _hsv_range(rgb) -> dict:
    """A settings file's colour range around ``rgb`` (OpenCV HSV, H in 0..180)."""
    h, s, _ = colorsys.rgb_to_hsv(*(c / 255 for c in rgb))
    hue = round(h * 180)
    return {
        "segmentation": {
            "hsv_low": [hue - 10, max(round(s * 255) - 90, 0), 50],
            "hsv_high": [hue + 10, 255, 255],
        }
    }


@pytest.fixture(scope="module")
def lab_recording():
    """The truth at 1 ms (for clouds between pose ticks), poses at 100 Hz, clouds at 15 Hz."""
    rec = generate_recording(generic_model(LENGTH, MASS, N), n_frames=150, seed=4)
    truth = rec.positions
    t = np.arange(len(truth)) * 10.0  # ms
    t_fine = np.arange(0.0, t[-1] + 1.0)
    fine = np.stack(
        [np.interp(t_fine, t, truth[:, i, j]) for i in range(N) for j in range(3)], axis=1
    ).reshape(len(t_fine), N, 3)
    frames = render_recording(
        fine[CLOUD_PHASE_MS:], dt=0.001, fps=CLOUD_FPS, config=RenderConfig(rope_rgb=BLUE), seed=2
    )
    return truth, fine, frames, offsets_for(truth)


DEPTH_OPTICAL = "camera_depth_optical_frame"
# the depth sensor's optical frame: 40 mm beside the colour one, in the same tree
LINK_FROM_DEPTH_OPTICAL = LINK_FROM_OPTICAL @ np.array(
    [[1.0, 0, 0, -0.04], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
)


def _write_bag(
    path,
    storage: StoragePlugin,
    truth,
    frames,
    grippers,
    more_infos: dict | None = None,
    info_frame: str = OPTICAL,
    root: str = "world",
    robot: tuple[str, np.ndarray] | None = None,
    colour_info: bool = True,
) -> None:
    """``more_infos``: further CameraInfo topics, ``{topic: (K, width, height)}``, beside the colour one;
    ``info_frame``: the frame the CameraInfo messages name (the clouds name ``OPTICAL``); ``root``:
    the transform tree's root frame, in which the rope moves; ``robot``: ``(frame, root_from_frame)``,
    a robot frame on the tree the gripper poses are published in (default: ``root``); ``colour_info``:
    whether the clouds' own CameraInfo is recorded."""
    camera = frames[0].camera
    world_from_link = camera.world_from_camera @ np.linalg.inv(LINK_FROM_OPTICAL)
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    poses = poses_from_vertices(truth, grippers)
    pose_frame, tree = root, [_transform(T0_NS, root, "camera_link", world_from_link)]
    if robot is not None:
        pose_frame, root_from_robot = robot
        tree.append(_transform(T0_NS, root, pose_frame, root_from_robot))
        robot_from_root = np.linalg.inv(root_from_robot)
        poses = np.array([[matrix_to_pose(robot_from_root @ pose_matrix(q)) for q in p] for p in poses])
    ts = M.TYPESTORE
    with Writer(path, version=9, storage_plugin=storage) as w:
        tf = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        info = w.add_connection(TOPICS["info"], M.CAMERA_INFO, typestore=ts)
        points = w.add_connection(TOPICS["points"], M.POINT_CLOUD2, typestore=ts)
        pose = w.add_connection(TOPICS["poses"], M.POSE_ARRAY, typestore=ts)
        msg = M.T["tf2_msgs/msg/TFMessage"](
            transforms=[
                *tree,
                _transform(T0_NS, "camera_link", OPTICAL, LINK_FROM_OPTICAL),
                _transform(T0_NS, "camera_link", DEPTH_OPTICAL, LINK_FROM_DEPTH_OPTICAL),
            ]
        )
        w.write(tf, T0_NS, ts.serialize_cdr(msg, "tf2_msgs/msg/TFMessage"))
        if colour_info:
            w.write(info, T0_NS, M.camera_info(T0_NS, K, camera.width, camera.height, frame_id=info_frame))
        for topic, (K_, width, height) in (more_infos or {}).items():
            conn = w.add_connection(topic, M.CAMERA_INFO, typestore=ts)
            w.write(conn, T0_NS, M.camera_info(T0_NS, K_, width, height, frame_id=info_frame))
        clouds = {T0_NS + (CLOUD_PHASE_MS + f.step) * 1_000_000: f for f in frames}
        for k in range(len(truth)):
            stamp = T0_NS + k * 10_000_000
            for c in [c for c in clouds if c < stamp]:  # a cloud arrives 5 ms after its stamp
                f = clouds.pop(c)
                w.write(points, c + 5_000_000, M.point_cloud(c, f.xyz, f.rgb, frame_id=OPTICAL))
            w.write(pose, stamp, M.pose_array(stamp, poses[k], frame_id=pose_frame))


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3], ids=["mcap", "sqlite3"])
def test_a_ros2_bag_folder_gives_the_camera_from_tf_static_and_every_cloud(lab_recording, tmp_path, storage):
    truth, _, frames, grippers = lab_recording
    path = tmp_path / "rosbag2_clip"
    _write_bag(path, storage, truth, frames, grippers)
    clip = read_clip(path, ServiceConfig(grippers=grippers))
    assert clip.camera_source.startswith("/tf_static")
    np.testing.assert_allclose(clip.camera.world_from_camera, frames[0].camera.world_from_camera, atol=1e-9)
    assert clip.points_topic == TOPICS["points"] and clip.n_clouds == len(frames)
    stamps = [c[0] for c in clip.clouds()]
    assert stamps == sorted(stamps) and (stamps[0] - T0_NS) // 1_000_000 == CLOUD_PHASE_MS
    np.testing.assert_allclose(
        pose_matrix(clip.poses[10, 0])[:3, 3], poses_from_vertices(truth, grippers)[10, 0, :3], atol=1e-12
    )


def test_the_camera_pose_is_looked_up_for_the_clouds_frame(lab_recording, tmp_path):
    """Intrinsics stamped with another frame of the same camera (the depth sensor's, 40 mm off): the
    points are in their cloud's frame, and the camera pose is that frame's, not CameraInfo's."""
    truth, _, frames, grippers = lab_recording
    _write_bag(tmp_path / "clip", StoragePlugin.MCAP, truth, frames, grippers, info_frame=DEPTH_OPTICAL)
    clip = read_clip(tmp_path / "clip", ServiceConfig(grippers=grippers))
    assert clip.camera_source.endswith(f"-> {OPTICAL})")
    np.testing.assert_allclose(clip.camera.world_from_camera, frames[0].camera.world_from_camera, atol=1e-9)


def test_gripper_poses_in_the_robots_frame_are_moved_into_the_world(lab_recording, tmp_path):
    """A robot publishes its gripper poses in its base frame, linked to the world on ``/tf_static``:
    the clip's poses are the world-frame ones. With a tree rooted at the robot's base (no world frame
    at all), the base is the world: the camera is looked up from it, the poses kept as they are, and
    the clip says so. Poses in a frame the service config does not name were all refused before."""
    truth, _, frames, grippers = lab_recording
    want = poses_from_vertices(truth, grippers)
    c, s_ = np.cos(0.7), np.sin(0.7)
    world_from_base = np.array([[c, -s_, 0, 0.4], [s_, c, 0, -0.2], [0, 0, 1, 0.05], [0, 0, 0, 1.0]])
    _write_bag(
        tmp_path / "base", StoragePlugin.MCAP, truth, frames, grippers, robot=("base_link", world_from_base)
    )
    clip = read_clip(tmp_path / "base", ServiceConfig(grippers=grippers))
    assert clip.world_frame == "world" and clip.poses_from.startswith("base_link, moved into world")
    assert len(clip.poses) == len(truth)
    np.testing.assert_allclose(clip.poses[:, :, :3], want[:, :, :3], atol=1e-9)
    np.testing.assert_allclose(
        [pose_matrix(q)[:3, :3] for q in clip.poses[:, 0]],
        [pose_matrix(q)[:3, :3] for q in want[:, 0]],
        atol=1e-9,
    )
    _write_bag(tmp_path / "rooted", StoragePlugin.MCAP, truth, frames, grippers, root="base_link")
    clip = read_clip(tmp_path / "rooted", ServiceConfig(grippers=grippers))
    assert clip.world_frame == "base_link" and "frame_id: base_link" in clip.poses_from
    assert clip.camera_source.startswith("/tf_static (base_link")
    np.testing.assert_allclose(clip.camera.world_from_camera, frames[0].camera.world_from_camera, atol=1e-9)
    np.testing.assert_allclose(clip.poses[:, :, :3], want[:, :, :3], atol=1e-12)


def test_the_intrinsics_of_the_clouds_image_are_found_among_a_drivers_several(lab_recording, tmp_path):
    """A camera driver publishes its depth sensor's intrinsics (another size) and the aligned depth's
    (the colour ones again) beside the colour ones the cloud is registered to: the cloud's are taken
    without a ``--topic-camera-info``; of two that disagree at the cloud's size, the clouds' own fit
    decides, unless one is chosen."""
    truth, _, frames, grippers = lab_recording
    camera = frames[0].camera
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    depth = (np.array([[420.0, 0, 424], [0, 420, 240], [0, 0, 1]]), 848, 480)
    driver = {"/camera/camera/depth/camera_info": depth,
              "/camera/camera/aligned_depth_to_color/camera_info": (K, camera.width, camera.height)}  # fmt: skip
    _write_bag(tmp_path / "driver", StoragePlugin.MCAP, truth, frames, grippers, driver)
    clip = read_clip(tmp_path / "driver", ServiceConfig(grippers=grippers))
    assert (clip.camera.fx, clip.camera.width, clip.camera.height) == (camera.fx, camera.width, camera.height)
    other = {"/camera/ir/camera_info": (K * [[1.1], [1.1], [1]], camera.width, camera.height)}
    _write_bag(tmp_path / "two", StoragePlugin.MCAP, truth, frames, grippers, other)
    clip = read_clip(tmp_path / "two", ServiceConfig(grippers=grippers))  # two that disagree: the clouds tell
    assert "several camera info topics" in clip.intrinsics_from and abs(clip.camera.fx - camera.fx) < 0.5
    chosen = read_clip(
        tmp_path / "two", ServiceConfig(grippers=grippers), Topics(camera_info="/camera/ir/camera_info")
    )
    assert chosen.camera.fx == 1.1 * camera.fx and chosen.intrinsics_from == "/camera/ir/camera_info"


@pytest.mark.parametrize("infos", ["none", "another_size"])
def test_without_the_clouds_intrinsics_the_clouds_give_them(lab_recording, tmp_path, infos):
    """No CameraInfo recorded, or only one of another image (the driver's depth intrinsics beside
    clouds registered to colour): the organized clouds are their own calibration, and the clip says
    where its intrinsics came from. Before, the clip had no intrinsics or every cloud was dropped as
    of the wrong size."""
    truth, _, frames, grippers = lab_recording
    camera = frames[0].camera
    depth = {
        "/camera/camera/depth/camera_info": (np.array([[420.0, 0, 424], [0, 420, 240], [0, 0, 1]]), 848, 480)
    }
    more = depth if infos == "another_size" else None
    _write_bag(tmp_path / "clip", StoragePlugin.MCAP, truth, frames, grippers, more, colour_info=False)
    clip = read_clip(tmp_path / "clip", ServiceConfig(grippers=grippers))
    got = clip.camera
    assert (got.width, got.height) == (camera.width, camera.height)
    np.testing.assert_allclose(
        [got.fx, got.fy, got.cx, got.cy], [camera.fx, camera.fy, camera.cx, camera.cy], atol=0.5
    )
    assert clip.intrinsics_from.startswith(f"the {camera.width}x{camera.height} clouds themselves")
    assert ("848x480" in clip.intrinsics_from) == (infos == "another_size")
    assert len(list(clip.clouds())) == len(frames)


def test_clouds_without_intrinsics_that_no_pinhole_made_are_refused(lab_recording, tmp_path):
    """No CameraInfo, and clouds whose points are not where one pinhole camera's rays put them (the
    pixels shuffled): one line naming what is missing, no guess."""
    truth, _, frames, grippers = lab_recording
    rng = np.random.default_rng(0)

    def shuffled(f):
        flat = f.xyz.reshape(-1, 3)
        return replace(f, xyz=flat[rng.permutation(len(flat))].reshape(f.xyz.shape))

    _write_bag(
        tmp_path / "clip",
        StoragePlugin.MCAP,
        truth,
        [shuffled(f) for f in frames],
        grippers,
        colour_info=False,
    )
    with pytest.raises(
        CalibrationError, match=r"no camera intrinsics for the clouds' \d+x\d+ image \(no sensor_msgs"
    ):
        read_clip(tmp_path / "clip", ServiceConfig(grippers=grippers))


def test_the_lab_clip_is_tracked_with_its_colour_range(lab_recording, tmp_path):
    """Tracked from the generic model within a few millimetres of the rope at the track's own times
    (a grid from the first cloud's stamp, 3 ms off the pose ticks); the default colour range (an
    orange rope) finds none of it. Another lab, whose driver writes a missing point as (0, 0, 0),
    whose robot publishes the poses in its base frame and which recorded no CameraInfo, gets the
    same track within a tenth of a millimetre."""
    truth, fine, frames, grippers = lab_recording
    path = tmp_path / "rosbag2_clip"
    _write_bag(path, StoragePlugin.MCAP, truth, frames, grippers)
    settings = tmp_path / "perception.yaml"
    settings.write_text(yaml.safe_dump(_hsv_range(BLUE)))
    clip = read_clip(path, ServiceConfig(grippers=grippers))
    model = generic_model(LENGTH, MASS, N)
    track = track_clip(clip, model, grippers, load_config(settings))
    at = CLOUD_PHASE_MS + 10 * np.arange(track.n_frames)
    err = np.linalg.norm(track.positions - fine[at], axis=-1)
    assert err.mean() < 0.004, err.mean(1)
    assert track.coverage[2:-2].min() > 0.8
    blind = track_clip(clip, model, grippers, load_config(None))
    assert blind.coverage[2:-2].max() == 0.0
    zeros = [replace(f, xyz=np.where(np.isfinite(f.xyz), f.xyz, 0.0).astype(np.float32)) for f in frames]
    base = np.array([[0, -1.0, 0, 0.3], [1.0, 0, 0, 0.1], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])
    other = tmp_path / "another_lab"
    _write_bag(
        other, StoragePlugin.MCAP, truth, zeros, grippers, robot=("base_link", base), colour_info=False
    )
    theirs = track_clip(
        read_clip(other, ServiceConfig(grippers=grippers)), model, grippers, load_config(settings)
    )
    assert np.abs(theirs.positions - track.positions).max() < 1e-4
