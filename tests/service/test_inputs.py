"""Bad inputs are rejected with a counter and the loop goes on; modes follow the inputs. Wall time is a
fake clock throughout: nothing here depends on how fast the machine is."""

import threading

import numpy as np
import pytest

from perception import Camera
from service import messages as M
from service.estimator import Estimator
from service.fusion import FusionWorker
from service.geometry import pose_matrix
from tests.service.conftest import FakeClock, make_config
from tests.service.open_loop_tracker import OpenLoopTracker

GOOD = np.array([[-0.4, 0, 0.5, 0, 0, 0, 1], [0.4, 0, 0.5, 0, 0, 1, 0]], dtype=float)
T0 = 1_700_000_000 * 10**9


@pytest.fixture
def est(model):
    """An estimator on a fake wall clock (``est.clock``)."""
    return Estimator(make_config(), model, OpenLoopTracker(model, settle_steps=20), clock=FakeClock())


def test_bad_poses_counted_and_loop_continues(est):
    assert est.on_poses(M.pose_array(T0, GOOD))
    assert est.tick(T0) is not None
    bad = [
        b"not cdr at all",
        M.pose_array(T0 + 1, np.where(np.eye(2, 7, dtype=bool), np.nan, GOOD)),
        M.pose_array(T0 - 10**7, GOOD),  # out of order
        M.pose_array(T0 + 2, GOOD[:1]),
    ]  # one pose
    for raw in bad:
        assert not est.on_poses(raw)
    assert est.on_poses(M.pose_array(T0 + 10**7, GOOD))
    for k in range(3):
        assert est.tick(T0 + (k + 1) * 10**7) is not None
    rejected = est.status()["rejected"]
    assert rejected == {
        "ee_poses:malformed_cdr": 1,
        "ee_poses:nan_pose": 1,
        "ee_poses:out_of_order": 1,
        "ee_poses:wrong_pose_count": 1,
    }
    assert np.isfinite(est.estimate.x).all()


def test_stale_stamp_rejected(est):
    assert est.on_poses(M.pose_array(T0 + 5 * 10**9, GOOD))
    cloud = M.point_cloud(T0, np.ones((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8))
    est.on_camera_info(M.camera_info(T0, np.diag([100.0, 100, 1]), 4, 4))
    with pytest.raises(M.InputError, match="stale"):
        est.decode_cloud(cloud)


def test_bad_clouds_rejected(est):
    worker = FusionWorker(est)
    est.cfg.limits.max_cloud_bytes = 10_000
    worker.submit(bytes(20_000))  # too large
    for raw, reason in [
        (b"garbage", "malformed_cdr"),
        (M.vertices_cloud(T0, np.zeros((5, 3)), np.zeros(5)), "wrong_point_fields"),
        (
            M.point_cloud(T0, np.ones((1, 16, 3), np.float32), np.zeros((1, 16, 3), np.uint8)),
            "no_camera_info",
        ),
        (
            M.point_cloud(T0, np.full((4, 4, 3), np.nan, np.float32), np.zeros((4, 4, 3), np.uint8)),
            "empty_cloud",
        ),
        (M.point_cloud(T0, np.ones((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8)), "no_camera_info"),
    ]:
        with pytest.raises(M.InputError) as err:
            est.decode_cloud(raw)
        assert err.value.reason == reason
    assert est.status()["rejected"] == {"points:too_large": 1}


def test_a_cloud_without_its_camera_info_is_read_with_its_own_intrinsics(est):
    """No CameraInfo yet, or one of another image size (a driver's depth intrinsics beside clouds
    registered to colour): the organized cloud gives its intrinsics, kept per image size; a cloud
    that fits no pinhole camera is still refused by the reason it was before."""
    cam = Camera(250.0, 251.0, 161.0, 143.0, 320, 288)
    depth = np.random.default_rng(0).uniform(0.8, 2.0, (cam.height, cam.width, 1))
    xyz = (cam.ray_directions() * depth).astype(np.float32)
    rgb = np.zeros(xyz.shape, np.uint8)
    assert est.on_poses(M.pose_array(T0, GOOD))
    cloud = est.decode_cloud(M.point_cloud(T0 + 1, xyz, rgb))
    got = [cloud.camera.fx, cloud.camera.fy, cloud.camera.cx, cloud.camera.cy]
    np.testing.assert_allclose(got, [250.0, 251.0, 161.0, 143.0], atol=1e-3)
    est.on_camera_info(M.camera_info(T0, np.diag([420.0, 420, 1]), 848, 480))
    assert est.decode_cloud(M.point_cloud(T0 + 2, xyz, rgb)).camera.fx == cloud.camera.fx
    assert est.status()["counts"]["intrinsics_from_cloud"] == 1  # fitted once for 320x288
    shuffled = xyz.reshape(-1, 3)[np.random.default_rng(1).permutation(xyz.size // 3)].reshape(xyz.shape)
    small = M.point_cloud(T0 + 3, shuffled[:100, :120], rgb[:100, :120])
    with pytest.raises(M.InputError, match="cloud_size_mismatch"):
        est.decode_cloud(small)
    est.on_camera_info(M.camera_info(T0, np.diag([300.0, 300, 1]), 320, 288))  # now of the clouds' size
    assert est.decode_cloud(M.point_cloud(T0 + 4, xyz, rgb)).camera.fx == 300.0


def test_an_unorganized_cloud_is_put_on_its_camera_info_grid(est):
    """A cloud sent as one row of the pixels with depth, shuffled (RealSense's pointcloud filter),
    decodes to the organized cloud it was made from, in the camera frame or published in the world
    frame; the grid comes from CameraInfo, so without one it is refused by that reason."""
    cam = Camera(250.0, 251.0, 161.0, 143.0, 320, 288)
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.8, 2.0, (cam.height, cam.width, 1))
    depth[rng.random(depth.shape) < 0.3] = np.nan
    xyz = (cam.ray_directions() * depth).astype(np.float32)
    rgb = rng.integers(0, 256, xyz.shape, dtype=np.uint8)
    seen = np.isfinite(xyz[..., 2]).ravel()
    order = rng.permutation(int(seen.sum()))
    flat_xyz, flat_rgb = xyz.reshape(-1, 3)[seen][order][None], rgb.reshape(-1, 3)[seen][order][None]
    assert est.on_poses(M.pose_array(T0, GOOD))
    with pytest.raises(M.InputError, match="no_camera_info"):
        est.decode_cloud(M.point_cloud(T0 + 1, flat_xyz, flat_rgb))
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    est.on_camera_info(M.camera_info(T0, K, cam.width, cam.height))
    organized = est.decode_cloud(M.point_cloud(T0 + 2, xyz, rgb))
    flat = est.decode_cloud(M.point_cloud(T0 + 3, flat_xyz, flat_rgb))
    np.testing.assert_array_equal(flat.xyz, organized.xyz)
    np.testing.assert_array_equal(flat.rgb[seen.reshape(xyz.shape[:2])], rgb[seen.reshape(xyz.shape[:2])])
    assert (flat.camera.width, flat.camera.height, flat.camera.cx) == (320, 288, cam.cx)
    T = pose_matrix(est.camera_pose)  # published in the world frame: moved back first
    world = (flat_xyz[0] @ T[:3, :3].T + T[:3, 3]).astype(np.float32)[None]
    moved = est.decode_cloud(M.point_cloud(T0 + 4, world, flat_rgb, frame_id=est.cfg.frame_id))
    np.testing.assert_allclose(moved.xyz, organized.xyz, atol=1e-5)
    assert est.status()["counts"]["clouds_organized"] == 2


def test_a_late_stamped_cloud_counts_as_taken_its_delay_earlier(model):
    """``camera.stamp_delay_s``: a driver stamping its clouds 50 ms late; the cloud is dated when it
    was taken, on the poses' clock (what a message-clock service fuses it at); 0 leaves it as stamped."""
    for delay, want in ((0.05, T0 - 50_000_000), (0.0, T0)):
        est = Estimator(
            make_config(camera={"stamp_delay_s": delay}), model, OpenLoopTracker(model), clock=FakeClock()
        )
        est.on_camera_info(M.camera_info(T0, np.diag([100.0, 100, 1]), 4, 4))
        xyz = np.ones((4, 4, 3), np.float32)
        cloud = est.decode_cloud(M.point_cloud(T0, xyz, np.zeros((4, 4, 3), np.uint8)))
        assert cloud.stamp_ns == want


def test_cloud_flood_rejected(est):
    """Token bucket at ``max_cloud_rate_hz`` (60), burst of 3: exact counts on a fake clock."""
    worker = FusionWorker(est)  # not started: nothing consumes the slot
    raw = M.point_cloud(T0, np.zeros((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8))
    rate = est.cfg.limits.max_cloud_rate_hz
    assert rate == 60

    def flooded():
        return est.status()["rejected"].get("points:flood", 0)

    for _ in range(20):  # all at one instant: the burst of 3 passes, the rest is refused
        worker.submit(raw)
    assert flooded() == 17
    assert est.status()["dropped"]["cloud_superseded"] == 2  # the burst replaced each other in the slot
    est.clock.advance(1.5 / rate)  # a token and a half: one more cloud, not two
    worker.submit(raw)
    worker.submit(raw)
    assert flooded() == 18
    est.clock.advance(10.0)  # a long pause refills only up to the burst
    for _ in range(4):
        worker.submit(raw)
    assert flooded() == 19


def test_modes_follow_inputs(model):
    cfg = make_config(timeouts={"pose_s": 0.3, "cloud_s": 0.5, "stale_s": 1.0})
    clock = FakeClock()
    est = Estimator(cfg, model, OpenLoopTracker(model, settle_steps=20), clock=clock)
    assert est.mode() == "waiting"
    est.on_poses(M.pose_array(T0, GOOD))
    est.tick(T0)
    assert est.mode() == "open-loop"  # poses, no clouds
    est.fused_at = est.now()
    assert est.mode() == "tracking"
    clock.advance(0.25)  # poses and the cloud still within their timeouts
    assert est.mode() == "tracking"
    clock.advance(0.15)  # poses stop: 0.4 s > pose_s
    assert est.mode() == "waiting"
    assert est.status()["input_age_s"]["ee_poses"] == pytest.approx(0.4)
    est.on_poses(M.pose_array(T0 + 4 * 10**8, GOOD))  # poses again; the last cloud is 0.4 s old
    assert est.mode() == "tracking"
    clock.advance(0.2)  # the cloud is 0.6 s old (> cloud_s), the poses 0.2 s
    assert est.mode() == "open-loop"


def test_fused_tracker_keeps_the_compiled_step(est, model):
    """Fusion swaps in a tracker copy corrected in a worker (which has no compiled step of ours):
    the copy must go on with this side's step, not fall back to the eager one."""
    est.on_poses(M.pose_array(T0, GOOD))
    est.tick(T0)
    from deform.compiled import CompiledStep

    step = CompiledStep(model, enabled=False)  # the eager fallback: no compile time in the test
    est.use_step(step)
    est.on_camera_info(M.camera_info(T0, np.diag([100.0, 100, 1]), 4, 4))
    cloud = est.decode_cloud(
        M.point_cloud(T0 + 1, np.ones((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8))
    )
    before = est.tracker
    FusionWorker(est).fuse(cloud)
    assert est.tracker is not before and est.tracker.step_fn is step


def test_fusion_defers_to_a_running_predict_for_a_bounded_time(est):
    """While a predict runs the next fusion waits (counted), at most ``max_yield_s``, and goes on
    as soon as the predict ends; without a running predict it does not wait at all. (Fake clock:
    the bounds are exact, whatever the machine's load.)"""
    busy = threading.Event()
    worker = FusionWorker(est, yield_to=busy, max_yield_s=0.15)
    clock = FakeClock()
    worker.clock, worker.sleep = clock, clock.sleep
    poll = 0.002  # _yield's polling period: the wait ends at most one period after its cause
    worker._yield()
    assert clock.sleeps == 0 and "fusion_deferred" not in est.stats.snapshot()["counts"]
    busy.set()
    t = clock()
    worker._yield()  # the predict never ends: bounded
    assert 0.15 <= clock() - t < 0.15 + poll + 1e-9
    worker.max_yield_s = 2.0
    t = clock()
    clock.call_at(t + 0.03, busy.clear)  # the predict ends after 30 ms
    worker._yield()  # fusion goes on then, long before the bound
    assert 0.03 <= clock() - t < 0.03 + poll + 1e-9
    assert not busy.is_set()
    assert est.stats.snapshot()["counts"]["fusion_deferred"] == 2
    worker.stop()
    busy.set()
    t = clock()
    worker._yield()  # a stopping worker does not wait
    assert clock() == t


def test_frames_poses_in_another_frame_refused_a_world_cloud_moved_into_the_camera(est):
    assert not est.on_poses(M.pose_array(T0, GOOD, frame_id="base_link"))
    assert not est.on_camera_pose(M.pose_stamped(T0, [0, 0, 1, 0, 0, 0, 1], frame_id="base_link"))
    assert est.status()["rejected"] == {"ee_poses:wrong_frame": 1, "camera_pose:wrong_frame": 1}
    assert est.on_poses(M.pose_array(T0, GOOD, frame_id=""))  # no frame: taken as the world
    # camera 1 m above the origin, turned 90 degrees about z
    pose = np.array([0.0, 0.0, 1.0, 0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    assert est.on_camera_pose(M.pose_stamped(T0, pose))
    est.on_camera_info(M.camera_info(T0, np.diag([100.0, 100, 1]), 2, 2))
    cam = np.array([[[0.1, 0.2, 0.5], [0.0, 0.0, 1.0]], [[-0.3, 0.1, 2.0], [0.2, -0.2, 0.7]]], np.float32)
    world = cam @ np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]], np.float32) + np.float32([0, 0, 1])
    rgb = np.zeros((2, 2, 3), np.uint8)
    as_camera = est.decode_cloud(M.point_cloud(T0 + 1, cam, rgb, frame_id="camera"))
    as_world = est.decode_cloud(M.point_cloud(T0 + 2, world, rgb, frame_id="world"))
    assert np.allclose(as_camera.xyz, cam) and np.allclose(as_world.xyz, cam, atol=1e-6)
    slashed = est.decode_cloud(M.point_cloud(T0 + 3, world, rgb, frame_id="/world"))  # a tf-style name
    assert np.allclose(slashed.xyz, cam, atol=1e-6)


def test_status_reports_the_rope_lost_and_found_counts_through_a_worker_copy(model):
    """The tracker's loss counts reach status, also after fusion swapped in a copy of the tracker
    packed for a worker process."""
    from perception import Tracker
    from service.workers import pack_tracker, unpack_tracker

    est = Estimator(make_config(), model, Tracker(model), clock=FakeClock())
    assert est.status()["rope"]["state"] == "tracking" and est.status()["rope"]["lost"] == 0
    est.tracker.health.lose()
    est.tracker.health.recover(redetected=True)
    est.tracker = unpack_tracker(pack_tracker(est.tracker, model), model)
    rope = est.status()["rope"]
    assert (rope["lost"], rope["recovered"], rope["redetected"]) == (1, 1, 1)
    assert Estimator(make_config(), model, OpenLoopTracker(model), clock=FakeClock()).status()["rope"] is None
