"""CDR round trips of every message the service speaks, and rejection of malformed ones."""

import numpy as np
import pytest

from service import messages as M
from service.config import Grippers
from service.geometry import (
    grips_from_poses,
    matrix_to_pose,
    pose_matrix,
    poses_from_vertices,
    quat_to_matrix,
    quat_x_axis,
)


def test_pose_array_round_trip():
    poses = np.array([[0.1, 0.2, 0.3, 0, 0, 0, 1], [0.4, 0.5, 0.6, 0, 0, 1, 0]], dtype=float)
    stamp, out = M.parse_pose_array(M.pose_array(1_700_000_000_123_456_789, poses))
    assert stamp == 1_700_000_000_123_456_789
    np.testing.assert_array_equal(out, poses)


def test_organized_cloud_round_trip():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(6, 7, 3)).astype(np.float32)
    xyz[0, :3] = np.nan
    rgb = rng.integers(0, 256, (6, 7, 3)).astype(np.uint8)
    stamp, xyz2, rgb2, frame = M.parse_point_cloud(M.point_cloud(42, xyz, rgb, "cam"))
    assert stamp == 42 and frame == "cam"
    np.testing.assert_array_equal(xyz2, xyz)
    np.testing.assert_array_equal(rgb2, rgb)


def test_a_drivers_cloud_layout_is_read():
    """PCL's PointXYZRGBA layout as drivers publish it: 32-byte points (x y z, padding, rgba as uint32
    with alpha in the top byte, padding), padded rows, colour named "rgba"."""
    rng = np.random.default_rng(3)
    H, W, step, row = 3, 5, 32, 32 * 5 + 8
    xyz = rng.normal(size=(H, W, 3)).astype(np.float32)
    xyz[1, 2] = np.nan
    rgb = rng.integers(0, 256, (H, W, 3)).astype(np.uint8)
    data = np.zeros((H, row), np.uint8)
    pts = data[:, : step * W].reshape(H, W, step)
    pts[..., 0:12] = xyz.view(np.uint8).reshape(H, W, 12)
    packed = (
        (0xFF << 24)
        | (rgb[..., 0].astype(np.uint32) << 16)
        | (rgb[..., 1].astype(np.uint32) << 8)
        | rgb[..., 2]
    )
    pts[..., 16:20] = packed.astype("<u4").view(np.uint8).reshape(H, W, 4)
    PF = M.T["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=4 * i, datatype=M.FLOAT32, count=1) for i, n in enumerate("xyz")]
    fields.append(PF(name="rgba", offset=16, datatype=M.UINT32, count=1))
    msg = M.T[M.POINT_CLOUD2](
        header=M.header(9, "camera_color_optical_frame"), height=H, width=W, fields=fields,
        is_bigendian=False, point_step=step, row_step=row, data=data.reshape(-1), is_dense=False,
    )  # fmt: skip
    stamp, xyz2, rgb2, frame = M.parse_point_cloud(M.encode(msg, M.POINT_CLOUD2))
    assert stamp == 9 and frame == "camera_color_optical_frame"
    np.testing.assert_array_equal(xyz2, xyz)
    np.testing.assert_array_equal(rgb2, rgb)


def test_missing_points_of_every_driver_become_nan_and_float64_is_read():
    """A pixel without depth is NaN (Azure Kinect), (0, 0, 0) (RealSense's ordered clouds) or inf (out
    of range): all read as NaN, so that no zero becomes a surface at the lens (nor, in a cloud
    published in the world frame, a wall at the world's origin). x, y, z as float64 read as float32;
    a cloud with nothing measured is refused."""
    rng = np.random.default_rng(4)
    xyz = rng.normal(1.0, 0.2, size=(4, 5, 3))
    xyz[0, 0], xyz[1, 1], xyz[2, 2] = 0.0, np.inf, np.nan
    xyz[3, 3] = (0.0, 0.0, 1.2)  # a point on the optical axis is a measurement
    rgb = rng.integers(0, 256, (4, 5, 3)).astype(np.uint8)
    msg = M.decode(M.point_cloud(1, xyz.astype(np.float32), rgb), M.POINT_CLOUD2)
    _, got, _, _ = M.parse_point_cloud(M.encode(msg, M.POINT_CLOUD2))
    missing = ~np.isfinite(got).all(-1)
    assert missing.sum() == 3 and missing[0, 0] and missing[1, 1] and missing[2, 2]
    assert np.isnan(got[missing]).all() and np.array_equal(got[3, 3], np.float32([0.0, 0.0, 1.2]))
    # the same cloud with float64 coordinates (24 bytes, then the colour)
    PF = M.T["sensor_msgs/msg/PointField"]
    rec = np.zeros((4, 5), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("rgb", "<u4"), ("pad", "<u4")])
    rec["x"], rec["y"], rec["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    rec["rgb"] = (rgb[..., 0].astype(np.uint32) << 16) | (rgb[..., 1].astype(np.uint32) << 8) | rgb[..., 2]
    msg.fields = [PF(name=n, offset=8 * i, datatype=M.FLOAT64, count=1) for i, n in enumerate("xyz")]
    msg.fields.append(PF(name="rgb", offset=24, datatype=M.UINT32, count=1))
    msg.point_step, msg.row_step, msg.data = 32, 32 * 5, rec.view(np.uint8).reshape(-1)
    _, got64, rgb64, _ = M.parse_point_cloud(M.encode(msg, M.POINT_CLOUD2))
    assert got64.dtype == np.float32 and np.array_equal(rgb64, rgb)
    np.testing.assert_array_equal(got64, got)
    with pytest.raises(M.InputError, match="empty_cloud"):
        M.parse_point_cloud(M.point_cloud(1, np.zeros((2, 2, 3), np.float32), np.zeros((2, 2, 3), np.uint8)))


def test_colour_as_three_fields_is_read():
    """Clouds made in Python often carry colour as fields r, g, b: uint8, or float in 0..1 (Open3D)."""
    rng = np.random.default_rng(5)
    H, W = 3, 4
    xyz = rng.normal(1.0, 0.2, size=(H, W, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (H, W, 3)).astype(np.uint8)
    PF = M.T["sensor_msgs/msg/PointField"]
    for fmt, datatype, values in (("u1", M.UINT8, rgb), ("<f4", M.FLOAT32, rgb / 255.0)):
        rec = np.zeros(
            (H, W), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", fmt), ("g", fmt), ("b", fmt)]
        )
        rec["x"], rec["y"], rec["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
        rec["r"], rec["g"], rec["b"] = values[..., 0], values[..., 1], values[..., 2]
        size = np.dtype(fmt).itemsize
        fields = [PF(name=n, offset=4 * i, datatype=M.FLOAT32, count=1) for i, n in enumerate("xyz")]
        fields += [PF(name=n, offset=12 + size * i, datatype=datatype, count=1) for i, n in enumerate("rgb")]
        msg = M.T[M.POINT_CLOUD2](
            header=M.header(3, "cam"), height=H, width=W, fields=fields, is_bigendian=False,
            point_step=rec.itemsize, row_step=rec.itemsize * W, data=rec.view(np.uint8).reshape(-1), is_dense=True,
        )  # fmt: skip
        _, xyz2, rgb2, _ = M.parse_point_cloud(M.encode(msg, M.POINT_CLOUD2))
        np.testing.assert_array_equal(xyz2, xyz)
        np.testing.assert_array_equal(rgb2, rgb)


def test_vertices_camera_info_pose_stamped_round_trip():
    x = np.random.default_rng(1).normal(size=(13, 3))
    obs = np.arange(13) % 3 == 0
    stamp, x2, obs2 = M.parse_vertices(M.vertices_cloud(7, x, obs))
    assert stamp == 7
    np.testing.assert_array_equal(x2, x.astype(np.float32))
    np.testing.assert_array_equal(obs2, obs)
    K = np.array([[250.0, 0, 160], [0, 251, 144], [0, 0, 1]])
    _, K2, w, h = M.parse_camera_info(M.camera_info(3, K, 320, 288))
    assert (w, h) == (320, 288)
    np.testing.assert_array_equal(K2, K)
    pose = np.array([1, 2, 3, 0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    _, p2 = M.parse_pose_stamped(M.pose_stamped(5, pose))
    np.testing.assert_allclose(p2, pose)


def test_shape_marker_round_trip():
    """``{ns}/shape``: the vertices as RViz's line strip, read back as the client reads them."""
    x = np.random.default_rng(2).normal(size=(12, 3))
    raw = M.shape_marker(1_700_000_000_000_000_009, x, "base_link", "rope1")
    stamp, x2 = M.parse_shape_marker(raw)
    assert stamp == 1_700_000_000_000_000_009
    np.testing.assert_array_equal(x2, x)  # float64 points: nothing lost
    msg = M.decode(raw, M.MARKER)
    assert msg.header.frame_id == "base_link" and msg.ns == "rope1" and msg.type == 4  # LINE_STRIP


def test_camera_info_is_read_in_ros_pixel_convention():
    """A driver's K puts pixel (u, v)'s centre at the integers (ROS, OpenCV); perception's Camera at
    j + 1/2. A point on the ray through ROS pixel (10, 7) must land in column 10, row 7 of ours, at its
    centre, and what we write is in ROS's convention."""
    from perception import Camera

    K_ros = np.array([[300.0, 0, 211.7], [0, 300.0, 118.4], [0, 0, 1]])
    raw = M.encode(
        M.T[M.CAMERA_INFO](
            header=M.header(3, "camera_color_optical_frame"),
            height=240,
            width=424,
            distortion_model="plumb_bob",
            d=np.zeros(5),
            k=K_ros.reshape(9),
            r=np.eye(3).reshape(9),
            p=np.zeros(12),
            binning_x=0,
            binning_y=0,
            roi=M.T["sensor_msgs/msg/RegionOfInterest"](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
            ),
        ),
        M.CAMERA_INFO,
    )
    _, K, w, h = M.parse_camera_info(raw)
    cam = Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h)
    z = 1.3
    point = np.array([(10 - K_ros[0, 2]) / 300.0 * z, (7 - K_ros[1, 2]) / 300.0 * z, z])
    (u, v), _ = cam.project(point)
    np.testing.assert_allclose((u, v), (10.5, 7.5), atol=1e-9)
    np.testing.assert_allclose(cam.ray_directions()[7, 10] * z, point, atol=1e-9)
    written = M.decode(M.camera_info(3, K, w, h), M.CAMERA_INFO)
    np.testing.assert_allclose(np.asarray(written.k).reshape(3, 3), K_ros, atol=1e-12)
    np.testing.assert_allclose(np.asarray(written.p)[[2, 6]], K_ros[[0, 1], 2], atol=1e-12)


def test_schema_text_is_ros2():
    text = M.definition(M.POSE_ARRAY)
    assert "builtin_interfaces/Time stamp" in text and "MSG: geometry_msgs/Pose" in text


@pytest.mark.parametrize("raw", [b"", b"\x00\x01\x00\x00garbage", bytes(range(256))])
def test_malformed_cdr_rejected(raw):
    with pytest.raises(M.InputError) as err:
        M.parse_pose_array(raw)
    assert err.value.reason == "malformed_cdr"


def test_bad_pose_content_rejected():
    nan = np.array([[np.nan, 0, 0, 0, 0, 0, 1], [0, 0, 0, 0, 0, 0, 1.0]])
    with pytest.raises(M.InputError, match="nan_pose"):
        M.parse_pose_array(M.pose_array(1, nan))
    with pytest.raises(M.InputError, match="wrong_pose_count"):
        M.parse_pose_array(M.pose_array(1, np.tile([0, 0, 0, 0, 0, 0, 1.0], (3, 1))))
    with pytest.raises(M.InputError, match="bad_quaternion"):
        M.parse_pose_array(M.pose_array(1, np.tile([0, 0, 0, 0, 0, 0, 3.0], (2, 1))))


def test_wrong_point_fields_rejected():
    # a vertices cloud has no rgb field: refused as an input cloud
    with pytest.raises(M.InputError) as err:
        M.parse_point_cloud(M.vertices_cloud(1, np.zeros((4, 3)), np.zeros(4)))
    assert err.value.reason == "wrong_point_fields"
    msg = M.decode(
        M.point_cloud(1, np.zeros((2, 2, 3), np.float32), np.zeros((2, 2, 3), np.uint8)), M.POINT_CLOUD2
    )
    msg.fields[3].name = "intensity"
    with pytest.raises(M.InputError, match="wrong_point_fields"):
        M.parse_point_cloud(M.encode(msg, M.POINT_CLOUD2))


def test_gripper_geometry_round_trip():
    g = Grippers(first={"d0": 0.01, "d1": 0.03}, last={"d0": 0.0, "d1": 0.025})
    rng = np.random.default_rng(2)
    x = rng.normal(size=(13, 3))
    for i0, i1, d in ((0, 1, 0.02), (12, 11, 0.025)):
        u = x[i1] - x[i0]
        x[i1] = x[i0] + d * u / np.linalg.norm(u)
    np.testing.assert_allclose(grips_from_poses(poses_from_vertices(x, g), g), x[[0, 1, 11, 12]], atol=1e-12)
    pose = np.array([0.1, -1.0, 0.5, -0.5, 0.5, -0.5, 0.5])
    np.testing.assert_allclose(pose_matrix(matrix_to_pose(pose_matrix(pose))), pose_matrix(pose), atol=1e-12)


def test_gripper_axis_other_than_x_round_trip():
    """A hand that holds the rope along its y axis (first) or its -z axis (last): poses made for that
    convention give the vertices back, and their rotation turns the named axis onto the rope."""
    g = Grippers(
        first={"d0": 0.01, "d1": 0.03, "axis": [0, 2, 0]}, last={"d0": 0.0, "d1": 0.025, "axis": [0, 0, -1]}
    )
    assert g.first.axis == [0.0, 1.0, 0.0]
    rng = np.random.default_rng(4)
    x = rng.normal(size=(8, 10, 3))
    for i0, i1, d in ((0, 1, 0.02), (9, 8, 0.025)):
        u = x[:, i1] - x[:, i0]
        x[:, i1] = x[:, i0] + d * u / np.linalg.norm(u, axis=-1, keepdims=True)
    poses = poses_from_vertices(x, g)
    np.testing.assert_allclose(grips_from_poses(poses, g), x[:, [0, 1, 8, 9]], atol=1e-12)
    u = (x[:, 1] - x[:, 0]) / 0.02
    np.testing.assert_allclose(quat_to_matrix(poses[:, 0, 3:7])[..., :, 1], u, atol=1e-12)
    # the same poses read with the default +x put the rope elsewhere
    assert np.abs(grips_from_poses(poses, Grippers()) - x[:, [0, 1, 8, 9]]).max() > 0.01


def test_gripper_axis_must_be_a_direction():
    with pytest.raises(ValueError, match="axis"):
        Grippers(first={"d0": 0.0, "d1": 0.03, "axis": [0, 0, 0]})
    with pytest.raises(ValueError):
        Grippers(first={"d0": 0.0, "d1": 0.03, "axis": [1, 0]})


def test_gripper_axis_is_the_rotations_first_column():
    """grips_from_poses reads only the +x axis of each pose: the same as the full rotation's first
    column, for any roll about it (poses_from_vertices above only makes zero-roll quaternions)."""
    q = np.random.default_rng(3).normal(size=(50, 2, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    np.testing.assert_allclose(quat_x_axis(q), quat_to_matrix(q)[..., :, 0], atol=1e-12)
