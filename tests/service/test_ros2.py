"""ROS 2 on rmw_zenoh without a bridge, checked against an independent implementation of its protocol
(zenoh-ros2-sdk): its publishers drive the service, its subscriber receives the vertices and the
shape line, its graph query lists the service's topics with their types. The SDK gets the message
definitions from a local folder (it would otherwise fetch them with git)."""

import json
import re
import threading
import time

import numpy as np
import pytest

from service import messages as M
from service import ros2
from service.node import Service
from tests.service.conftest import make_config, wait_for

sdk = pytest.importorskip("zenoh_ros2_sdk")
pytestmark = pytest.mark.zenoh

TYPES = (M.POSE_ARRAY, M.POINT_CLOUD2, M.MARKER, M.CAMERA_INFO)
WAIT_S = 30.0  # status conditions (a loaded machine starts the service slowly)
GOOD = np.array([[-0.4, 0, 0.5, 0, 0, 0, 1], [0.4, 0, 0.5, 0, 0, 1, 0]], dtype=float)


def write_definitions(root, typenames) -> None:
    """One ``<pkg>/msg/<Name>.msg`` per type and dependency, split from the ros2msg schema text."""
    for typename in typenames:
        text = M.definition(typename)
        sections = re.split(r"\n=+\nMSG: ", text)
        names = [typename] + [s.split("\n", 1)[0].strip() for s in sections[1:]]
        bodies = [sections[0]] + [s.split("\n", 1)[1] if "\n" in s else "" for s in sections[1:]]
        for name, body in zip(names, bodies):
            pkg, *_, msg = name.split("/")
            path = root / pkg / "msg" / f"{msg}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(body.strip() + "\n")


def sdk_cloud(get_message_class, height: int, width: int, stamp_ns: int) -> dict:
    """A PointCloud2 built from the SDK's own message classes: x y z float32, rgb packed in float32,
    points on a plane 1 m in front of the camera."""
    PF = get_message_class("sensor_msgs/msg/PointField")
    Header, Time = get_message_class("std_msgs/msg/Header"), get_message_class("builtin_interfaces/msg/Time")
    n = height * width
    xyz = np.zeros((n, 4), dtype="<f4")
    xyz[:, 0] = np.linspace(-0.2, 0.2, n)
    xyz[:, 2] = 1.0
    xyz[:, 3] = np.array([0x00FF8000] * n, dtype="<u4").view("<f4")
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return dict(
        header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id="camera"),
        height=height,
        width=width,
        fields=[PF(name=c, offset=4 * i, datatype=7, count=1) for i, c in enumerate(("x", "y", "z", "rgb"))],
        is_bigendian=False,
        point_step=16,
        row_step=16 * width,
        data=np.frombuffer(xyz.tobytes(), dtype=np.uint8),
        is_dense=False,
    )


@pytest.fixture
def robot(tmp_path, endpoint, monkeypatch):
    """The SDK, connected to the service's endpoint as a robot connects to its router."""
    from zenoh_ros2_sdk import message_registry, session

    write_definitions(tmp_path / "msgs", TYPES)
    monkeypatch.delenv("ZENOH_SESSION_CONFIG_URI", raising=False)
    monkeypatch.delenv("ZENOH_CONFIG_OVERRIDE", raising=False)
    monkeypatch.setattr(message_registry, "_registry", None)
    message_registry.get_registry(str(tmp_path / "msgs"))
    port = int(endpoint.rsplit(":", 1)[1])
    yield port
    if session.ZenohSession._instance is not None:
        session.ZenohSession._instance.close()


def test_keys_tokens_and_attachment_follow_rmw_zenoh():
    from zenoh_ros2_sdk.attachment import Attachment
    from zenoh_ros2_sdk.qos import DEFAULT_QOS_PROFILE
    from zenoh_ros2_sdk.utils import ros2_to_dds_type

    assert (
        ros2.dds_type(M.POSE_ARRAY)
        == ros2_to_dds_type(M.POSE_ARRAY)
        == "geometry_msgs::msg::dds_::PoseArray_"
    )
    assert ros2.topic_key(3, "/a/b", M.POSE_ARRAY).startswith(
        "3/a/b/geometry_msgs::msg::dds_::PoseArray_/RIHS01_"
    )
    assert ros2.qos_token() == DEFAULT_QOS_PROFILE.encode()
    assert ros2.mangle("/deform/rod1") == "%deform%rod1" and ros2.mangle("/") == "%"
    gid = bytes(range(16))
    raw = ros2.encode_attachment(7, 123456789, gid)
    theirs = Attachment.from_bytes(raw)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (7, 123456789, gid)
    assert ros2.decode_attachment(Attachment(9, 5, gid).to_bytes()) == (9, 5, gid)
    with pytest.raises(ValueError):
        ros2.encode_attachment(1, 1, b"short")
    with pytest.raises(ValueError):
        ros2.decode_attachment(b"\x00" * 10)


def test_service_type_hash_is_the_one_ros_publishes():
    from rosbags.typesys import Stores, get_typestore
    from zenoh_ros2_sdk.utils import compute_service_type_hash

    from service.ros2_predict import PREDICT_HASH, PREDICT_SRV, REQUEST, RESPONSE, register_service

    # the example in rmw_zenoh's docs/design.md, made by rosidl
    store = get_typestore(Stores.ROS2_HUMBLE)
    add = register_service("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b\n", "int64 sum\n", store)
    assert add == "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
    assert PREDICT_HASH == compute_service_type_hash(PREDICT_SRV, REQUEST, RESPONSE)  # the SDK's own
    assert ros2.topic_key(0, "/deform/rod1/predict", PREDICT_SRV).endswith(
        "/deform_msgs::srv::dds_::PredictShapes_/" + PREDICT_HASH
    )


def test_bad_ros_names_are_refused():
    from service.config import ServiceConfigError, load_config

    with pytest.raises(ServiceConfigError, match="not a ROS 2 name"):
        load_config(interface="ros2", namespace="deform/2rod")
    with pytest.raises(ServiceConfigError, match="not a ROS 2 name"):
        load_config(interface="ros2", ros2={"node": "my-node"})
    load_config(interface="zenoh", namespace="deform/2rod")  # a plain key may start with a digit


@pytest.mark.slow
def test_a_ros2_node_drives_the_service_and_receives_vertices(model, endpoint, robot):
    from zenoh_ros2_sdk import (
        ROS2Publisher,
        ROS2ServiceClient,
        ROS2Subscriber,
        get_message_class,
        get_topic_names_and_types,
    )

    from service.ros2_predict import PREDICT_SRV, REQUEST, RESPONSE

    cfg = make_config(endpoint, interface="ros2", timeouts={"pose_s": 2.0})
    got, cond = {"vertices": [], "shape": []}, threading.Condition()

    def keep(name):
        def callback(msg):
            with cond:
                got[name].append(msg)
                cond.notify_all()

        return callback

    with Service(cfg, model=model):
        kw = dict(router_ip="127.0.0.1", router_port=robot, domain_id=0)
        subs = [
            ROS2Subscriber("/deform/rod1/vertices", M.POINT_CLOUD2, keep("vertices"), **kw),
            ROS2Subscriber("/deform/rod1/shape", M.MARKER, keep("shape"), **kw),
        ]
        pub = ROS2Publisher("/deform/rod1/ee_poses", M.POSE_ARRAY, **kw)
        # the graph as `ros2 topic list -t` sees it, from the liveliness tokens
        end = time.monotonic() + 20
        while time.monotonic() < end:
            topics = dict(get_topic_names_and_types(**kw))
            if "/deform/rod1/points" in topics and "/deform/rod1/vertices" in topics:
                break
        assert topics["/deform/rod1/vertices"] == [M.POINT_CLOUD2]
        assert topics["/deform/rod1/shape"] == [M.MARKER]
        assert topics["/deform/rod1/ee_poses"] == [M.POSE_ARRAY]
        for name, typename in (("points", M.POINT_CLOUD2), ("camera_info", M.CAMERA_INFO)):
            assert topics[f"/deform/rod1/{name}"] == [typename]

        Header, Time = (
            get_message_class("std_msgs/msg/Header"),
            get_message_class("builtin_interfaces/msg/Time"),
        )
        Pose = get_message_class("geometry_msgs/msg/Pose")
        Point, Quat = (
            get_message_class("geometry_msgs/msg/Point"),
            get_message_class("geometry_msgs/msg/Quaternion"),
        )
        stop = threading.Event()

        def feed():
            k, t0 = 0, time.time_ns()
            while not stop.is_set():
                sec, nsec = divmod(t0 + k * 10_000_000, 1_000_000_000)
                poses = [
                    Pose(
                        position=Point(x=p[0], y=p[1], z=p[2]),
                        orientation=Quat(x=p[3], y=p[4], z=p[5], w=p[6]),
                    )
                    for p in GOOD
                ]
                pub.publish(header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id="world"), poses=poses)
                k += 1
                time.sleep(0.01)

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            with cond:
                assert cond.wait_for(lambda: len(got["vertices"]) >= 5 and len(got["shape"]) >= 5, 30)
        finally:
            stop.set()
            feeder.join()
        # the client library follows the same stream in ros2 mode
        from service.client import ShapeClient

        client_got = threading.Event()
        with ShapeClient(connect=[endpoint], interface="ros2") as rope:
            rope.subscribe(lambda stamp, x, observed: x.shape == (13, 3) and client_got.set())
            stop.clear()
            feeder = threading.Thread(target=feed, daemon=True)
            feeder.start()
            try:
                assert client_got.wait(30)
                assert rope.vertices()[1].shape == (13, 3)  # queries stay on plain keys
                # the robot's camera: an organised cloud is fused, an unorganised one refused
                cam = ROS2Publisher("/deform/rod1/points", M.POINT_CLOUD2, **kw)
                info = ROS2Publisher("/deform/rod1/camera_info", M.CAMERA_INFO, **kw)
                Roi = get_message_class("sensor_msgs/msg/RegionOfInterest")
                info.publish(
                    header=Header(stamp=Time(sec=1, nanosec=0), frame_id="camera"),
                    height=4,
                    width=4,
                    distortion_model="plumb_bob",
                    d=np.zeros(5),
                    k=np.array([4.0, 0, 2, 0, 4, 2, 0, 0, 1]),
                    r=np.eye(3).ravel(),
                    p=np.array([4.0, 0, 2, 0, 0, 4, 2, 0, 0, 0, 1, 0]),
                    binning_x=0,
                    binning_y=0,
                    roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
                )
                assert wait_for(lambda: "camera_info" in rope.status()["input_age_s"], WAIT_S)
                cam.publish(**sdk_cloud(get_message_class, 4, 4, time.time_ns()))
                assert wait_for(lambda: rope.status()["counts"].get("clouds_fused", 0) >= 1, WAIT_S), (
                    json.dumps(rope.status())
                )
                # unorganized (one row, as RealSense's pointcloud filter sends it): put on the 4x4 grid
                cam.publish(**sdk_cloud(get_message_class, 1, 16, time.time_ns()))
                assert wait_for(lambda: rope.status()["counts"].get("clouds_organized") == 1, WAIT_S), (
                    json.dumps(rope.status())
                )
                cam.close()
                info.close()
                # predict as a ROS 2 service: the SDK computes the type hash from the definition itself
                assert wait_for(lambda: rope.status()["predict_ready"], WAIT_S)
                caller = ROS2ServiceClient(
                    "/deform/rod1/predict",
                    PREDICT_SRV,
                    request_definition=REQUEST,
                    response_definition=RESPONSE,
                    timeout=60.0,
                    **kw,
                )
                plans = np.tile(GOOD, (3, 5, 1, 1))
                plans[:, :, :, 2] += np.linspace(0, 0.05, 5)[None, :, None]
                res = caller.call(plans=3, steps=5, poses=plans.ravel(), dt=0.0, return_steps="")
                assert res.error == "" and (res.plans, res.vertices) == (3, 13)
                assert list(res.steps) == [1, 2, 3, 4, 5] and len(res.overstretched) == 3
                shapes = np.asarray(res.positions).reshape(3, 5, 13, 3)
                assert np.allclose(
                    shapes[:, -1, 0], GOOD[0, :3] + [0, 0, 0.05], atol=1e-3
                )  # gripped end lifted
                bad = caller.call(plans=3, steps=5, poses=plans.ravel()[:-1], dt=0.0, return_steps="")
                assert bad.error.startswith("bad_shape") and bad.plans == 0
                caller.close()
            finally:
                stop.set()
                feeder.join()
        for s in subs:
            s.close()
        pub.close()

    cloud, line = got["vertices"][-1], got["shape"][-1]
    assert cloud.header.frame_id == "world" and cloud.width == 13
    rec = np.frombuffer(
        bytes(cloud.data),
        dtype=np.dtype(
            {
                "names": ["x", "y", "z"],
                "formats": ["<f4"] * 3,
                "offsets": [0, 4, 8],
                "itemsize": cloud.point_step,
            }
        ),
    )
    x = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
    # the gripped end vertices sit at the grippers the ROS node sent
    assert np.allclose(x[0], GOOD[0, :3], atol=1e-3) and np.allclose(x[-1], GOOD[1, :3], atol=1e-3)
    pts = np.array([[p.x, p.y, p.z] for p in line.points])
    assert line.type == 4 and line.header.frame_id == "world" and pts.shape == (13, 3)
    assert np.allclose(pts[0], GOOD[0, :3], atol=1e-3)


def test_a_ros2_predict_request_becomes_a_binary_request_the_pool_can_split():
    """The typed predict's request reaches predict as the binary format (plans as float32 behind a
    header, as ShapeClient sends them), so its plan count is readable without parsing and a large
    one is split."""
    from service import messages as M
    from service import predict_codec
    from service.ros2_predict import PREDICT_SRV, request_body

    plans = np.random.default_rng(4).normal(size=(200, 3, 2, 7))
    Req = M.T[f"{PREDICT_SRV}_Request"]
    cdr = M.encode(
        Req(plans=200, steps=3, poses=plans.ravel(), dt=0.01, return_steps="final"), f"{PREDICT_SRV}_Request"
    )
    raw = request_body(cdr)
    assert predict_codec.is_binary_request(raw) and predict_codec.request_plans(raw) == 200
    fields, decoded = predict_codec.decode_request(raw)
    assert fields == {"return": "final", "encoding": "binary", "dt": 0.01}
    assert len(raw) < plans.nbytes * 0.6  # float32 on the wire
    np.testing.assert_allclose(decoded, plans, rtol=1e-7, atol=1e-7)
