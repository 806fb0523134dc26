"""Bags read back: topics found by message type, header stamps, the camera from its topic or the
config; a bag without gripper poses or clouds is refused with one line."""

import numpy as np
import pytest

from calibrate.bags import Topics, read_clip
from calibrate.errors import CalibrationError
from service.bag import write_messages
from service.config import ServiceConfig
from service.geometry import poses_from_vertices


def test_topics_found_by_type_and_poses_read_back(clips):
    cfg = ServiceConfig(grippers=clips.grippers)
    clip = read_clip(clips.bags[0], cfg)
    truth = clips.truths[0]
    assert clip.poses.shape == (len(truth), 2, 7)
    np.testing.assert_allclose(
        clip.poses[:, :, :3], poses_from_vertices(truth, clips.grippers)[:, :, :3], atol=1e-9
    )
    assert np.all(np.diff(clip.pose_stamps_ns) == 10_000_000)
    assert clip.points_topic == "/deform/rod1/points" and clip.n_clouds == 15
    assert clip.camera_source == "/deform/rod1/camera_pose"
    clouds = list(clip.clouds())
    assert len(clouds) == 15 and clouds[0][1].shape == (clip.camera.height, clip.camera.width, 3)
    assert [c[0] for c in clouds] == sorted(c[0] for c in clouds)


def test_camera_pose_from_the_config_without_a_pose_topic(clips, tmp_path):
    path = tmp_path / "no_pose.mcap"
    write_messages(path, "deform/rod1", [m for m in clips.messages if m.name != "camera_pose"])
    clip = read_clip(path, ServiceConfig())
    assert clip.camera_source.startswith("config")


def test_a_chosen_topic_that_is_not_there_is_named(clips):
    with pytest.raises(CalibrationError, match="--topic-poses"):
        read_clip(clips.bags[0], ServiceConfig(), Topics(poses="/robot/poses"))


@pytest.mark.parametrize(("drop", "message"), [("ee_poses", "no gripper poses"), ("points", "no clouds")])
def test_a_bag_without_poses_or_clouds_is_refused(clips, tmp_path, drop, message):
    path = tmp_path / f"no_{drop}.mcap"
    write_messages(path, "deform/rod1", [m for m in clips.messages if m.name != drop])
    with pytest.raises(CalibrationError, match=message):
        read_clip(path, ServiceConfig())


def test_not_a_bag(tmp_path):
    path = tmp_path / "junk.mcap"
    path.write_bytes(b"not a bag at all")
    with pytest.raises(CalibrationError, match="not a readable"):
        read_clip(path, ServiceConfig())


def _flattened(messages):
    """The clip's clouds as RealSense's pointcloud filter sends them: one row of the pixels with
    depth, in another order."""
    from service import messages as M
    from service.bag import Message

    rng = np.random.default_rng(0)
    out = []
    for m in messages:
        if m.name == "points":
            stamp, xyz, rgb, frame = M.parse_point_cloud(m.data)
            seen = np.isfinite(xyz[..., 2]).ravel()
            order = rng.permutation(int(seen.sum()))
            flat_xyz, flat_rgb = xyz.reshape(-1, 3)[seen][order], rgb.reshape(-1, 3)[seen][order]
            m = Message(m.name, m.log_time, M.point_cloud(stamp, flat_xyz[None], flat_rgb[None], frame))
        out.append(m)
    return out


def test_an_unorganized_cloud_is_read_on_its_camera_info_grid(clips, tmp_path):
    """Unorganized clouds (height 1) give the clip the organized clouds they were made from, put on
    the CameraInfo's grid as the service puts them; without a CameraInfo the clip is refused by
    that name, and a bag whose only cloud is the service's own output by its fields."""
    from service.bag import Message

    flat = _flattened(clips.messages)
    path = tmp_path / "flat.mcap"
    write_messages(path, "deform/rod1", flat)
    cfg = ServiceConfig(grippers=clips.grippers)
    want, got = read_clip(clips.bags[0], cfg), read_clip(path, cfg)
    a, b = got.camera, want.camera
    assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (b.fx, b.fy, b.cx, b.cy, b.width, b.height)
    np.testing.assert_array_equal(a.world_from_camera, b.world_from_camera)
    pairs = list(zip(want.clouds(), got.clouds(), strict=True))
    assert len(pairs) == 15
    for (s0, xyz0, rgb0), (s1, xyz1, rgb1) in pairs:
        assert s0 == s1
        np.testing.assert_array_equal(xyz1, xyz0)
        np.testing.assert_array_equal(rgb1[np.isfinite(xyz0[..., 2])], rgb0[np.isfinite(xyz0[..., 2])])
    no_info = tmp_path / "flat_no_info.mcap"
    write_messages(no_info, "deform/rod1", [m for m in flat if m.name != "camera_info"])
    with pytest.raises(CalibrationError, match=r"unorganized.*CameraInfo"):
        read_clip(no_info, cfg)
    from service import messages as M

    vertices = [
        Message(m.name, m.log_time, M.vertices_cloud(m.log_time, np.zeros((5, 3)), np.zeros(5)))
        if m.name == "points"
        else m
        for m in clips.messages
    ]
    only_output = tmp_path / "vertices.mcap"
    write_messages(only_output, "deform/rod1", vertices)
    with pytest.raises(CalibrationError, match=r"no camera's clouds.*rgb"):
        read_clip(only_output, cfg)


@pytest.mark.parametrize(
    ("storage", "mode"),
    [("SQLITE3", "FILE"), ("SQLITE3", "MESSAGE"), ("MCAP", "MESSAGE"), ("MCAP", "STORAGE")],
)
def test_a_compressed_rosbag2_reads_as_the_plain_clip(clips, tmp_path, storage, mode):
    """`ros2 bag record --compression-mode file|message --compression-format zstd`, in either
    storage, and MCAP's own chunk compression: the same poses, stamps and clouds as the clip's
    plain MCAP file."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    from service import messages as M
    from service.bag import TYPES

    path = tmp_path / f"{storage}_{mode}".lower()
    writer = Writer(path, version=8, storage_plugin=StoragePlugin[storage])
    writer.set_compression(CompressionMode[mode], CompressionFormat.ZSTD)
    writer.open()
    connections = {}
    for m in clips.messages:
        if m.name not in connections:
            connections[m.name] = writer.add_connection(
                f"/deform/rod1/{m.name}", TYPES[m.name], typestore=M.TYPESTORE
            )
        writer.write(connections[m.name], m.log_time, m.data)
    writer.close()

    cfg = ServiceConfig(grippers=clips.grippers)
    plain, packed = read_clip(clips.bags[0], cfg), read_clip(path, cfg)
    assert packed.n_clouds == plain.n_clouds == 15
    np.testing.assert_array_equal(packed.pose_stamps_ns, plain.pose_stamps_ns)
    np.testing.assert_array_equal(packed.poses, plain.poses)
    for (ta, pa, ca), (tb, pb, cb) in zip(plain.clouds(), packed.clouds(), strict=True):
        assert ta == tb
        np.testing.assert_array_equal(pa, pb)
        np.testing.assert_array_equal(ca, cb)
