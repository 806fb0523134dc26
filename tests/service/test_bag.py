"""MCAP files as other tools read them: an independent ROS 2 reader (mcap-ros2-support) decodes the
inputs and the outputs, and every channel carries the QoS rosbag2 stores."""

import numpy as np
import pytest
import yaml

from service import bag
from service import messages as M

mcap_ros2 = pytest.importorskip("mcap_ros2.reader")

POSES = np.array([[-0.4, 0, 0.5, 0, 0, 0, 1], [0.4, 0, 0.5, 0, 0, 1, 0]], dtype=float)


def test_inputs_and_outputs_decode_with_an_independent_reader(tmp_path):
    x = np.linspace([-0.4, 0, 0.5], [0.4, 0, 0.5], 13)
    observed = np.arange(13) % 2 == 0
    path = tmp_path / "run.mcap"
    w = bag.McapWriter(path, "deform/rod1")
    w.write("ee_poses", 1_000, M.pose_array(1_000, POSES))
    w.write("vertices", 2_000, M.vertices_cloud(2_000, x, observed))
    w.close()
    got = {m.channel.topic: m for m in mcap_ros2.read_ros2_messages(str(path))}
    assert set(got) == {"/deform/rod1/ee_poses", "/deform/rod1/vertices"}
    poses = got["/deform/rod1/ee_poses"].ros_msg
    assert poses.header.frame_id == "world" and len(poses.poses) == 2
    assert poses.poses[1].position.x == pytest.approx(0.4) and poses.poses[1].orientation.z == pytest.approx(
        1.0
    )
    cloud = got["/deform/rod1/vertices"].ros_msg
    assert (cloud.width * cloud.height, cloud.header.stamp.nanosec) == (13, 2_000)
    assert [f.name for f in cloud.fields][:3] == ["x", "y", "z"]
    for m in got.values():
        qos = yaml.safe_load(m.channel.metadata["offered_qos_profiles"])
        assert qos[0]["reliability"] == 1 and qos[0]["depth"] == 10
    # replay reads the inputs back, never the outputs
    assert [m.name for m in bag.read_messages(path)] == ["ee_poses"]
