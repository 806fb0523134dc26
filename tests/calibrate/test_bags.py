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


def test_an_unorganized_cloud_is_refused_by_name(clips, tmp_path):
    """A cloud without its image grid (height 1, as ``create_cloud`` makes from a list of points) is
    named as such, not read as a rope the colour range cannot find."""
    from service import messages as M
    from service.bag import Message

    flat = []
    for m in clips.messages:
        if m.name == "points":
            stamp, xyz, rgb, frame = M.parse_point_cloud(m.data)
            m = Message(
                m.name, m.log_time, M.point_cloud(stamp, xyz.reshape(1, -1, 3), rgb.reshape(1, -1, 3), frame)
            )
        flat.append(m)
    path = tmp_path / "flat.mcap"
    write_messages(path, "deform/rod1", flat)
    with pytest.raises(CalibrationError, match="not organized"):
        read_clip(path, ServiceConfig())
