"""Bad inputs are rejected with a counter and the loop goes on; modes follow the inputs."""
import time

import numpy as np
import pytest

from service import messages as M
from service.estimator import Estimator
from service.fusion import FusionWorker
from service.tracking import OpenLoopTracker
from tests.service.conftest import make_config

GOOD = np.array([[-0.4, 0, 0.5, 0, 0, 0, 1], [0.4, 0, 0.5, 0, 0, 1, 0]], dtype=float)
T0 = 1_700_000_000 * 10**9


@pytest.fixture
def est(model):
    return Estimator(make_config(), model, OpenLoopTracker(model, settle_steps=20))


def test_bad_poses_counted_and_loop_continues(est):
    assert est.on_poses(M.pose_array(T0, GOOD))
    assert est.tick(T0) is not None
    bad = [b"not cdr at all", M.pose_array(T0 + 1, np.where(np.eye(2, 7, dtype=bool), np.nan, GOOD)),
           M.pose_array(T0 - 10**7, GOOD),                     # out of order
           M.pose_array(T0 + 2, GOOD[:1])]                     # one pose
    for raw in bad:
        assert not est.on_poses(raw)
    assert est.on_poses(M.pose_array(T0 + 10**7, GOOD))
    for k in range(3):
        assert est.tick(T0 + (k + 1) * 10**7) is not None
    rejected = est.status()["rejected"]
    assert rejected == {"ee_poses:malformed_cdr": 1, "ee_poses:nan_pose": 1, "ee_poses:out_of_order": 1,
                        "ee_poses:wrong_pose_count": 1}
    assert np.isfinite(est.estimate.x).all()


def test_stale_stamp_rejected(est):
    assert est.on_poses(M.pose_array(T0 + 5 * 10**9, GOOD))
    cloud = M.point_cloud(T0, np.zeros((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8))
    est.on_camera_info(M.camera_info(T0, np.diag([100.0, 100, 1]), 4, 4))
    with pytest.raises(M.InputError, match="stale"):
        est.decode_cloud(cloud)


def test_bad_clouds_rejected(est):
    worker = FusionWorker(est)
    est.cfg.limits.max_cloud_bytes = 10_000
    worker.submit(bytes(20_000))                                  # too large
    for raw, reason in [(b"garbage", "malformed_cdr"),
                        (M.vertices_cloud(T0, np.zeros((5, 3)), np.zeros(5)), "unorganized_cloud"),
                        (M.point_cloud(T0, np.full((4, 4, 3), np.nan, np.float32), np.zeros((4, 4, 3), np.uint8)), "empty_cloud"),
                        (M.point_cloud(T0, np.zeros((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8)), "no_camera_info")]:
        with pytest.raises(M.InputError) as err:
            est.decode_cloud(raw)
        assert err.value.reason == reason
    assert est.status()["rejected"] == {"points:too_large": 1}


def test_cloud_flood_rejected(est):
    worker = FusionWorker(est)   # not started: nothing consumes the slot
    raw = M.point_cloud(T0, np.zeros((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8))
    for _ in range(20):
        worker.submit(raw)
    st = est.status()
    assert st["rejected"].get("points:flood", 0) >= 16  # 60 Hz limit: a burst of 3 passes, then a trickle


def test_modes_follow_inputs(model):
    cfg = make_config(timeouts={"pose_s": 0.3, "cloud_s": 0.5, "stale_s": 1.0})
    est = Estimator(cfg, model, OpenLoopTracker(model, settle_steps=20))
    assert est.mode() == "waiting"
    est.on_poses(M.pose_array(T0, GOOD))
    est.tick(T0)
    assert est.mode() == "open-loop"        # poses, no clouds
    est.fused_at = est.now()
    assert est.mode() == "tracking"
    time.sleep(0.4)                          # poses stop
    assert est.mode() == "waiting"
    assert est.status()["input_age_s"]["ee_poses"] >= 0.3


def test_fused_tracker_keeps_the_compiled_step(est, model):
    """Fusion swaps in a tracker copy corrected in a worker (which has no compiled step of ours):
    the copy must go on with this side's step, not fall back to the eager one."""
    est.on_poses(M.pose_array(T0, GOOD))
    est.tick(T0)
    from deform.compiled import CompiledStep
    step = CompiledStep(model, enabled=False)  # the eager fallback: no compile time in the test
    est.use_step(step)
    est.on_camera_info(M.camera_info(T0, np.diag([100.0, 100, 1]), 4, 4))
    cloud = est.decode_cloud(M.point_cloud(T0 + 1, np.ones((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8)))
    before = est.tracker
    FusionWorker(est).fuse(cloud)
    assert est.tracker is not before and est.tracker.step_fn is step


def test_fusion_defers_to_a_running_predict_for_a_bounded_time(est):
    """While a predict runs the next fusion waits (counted), at most ``max_yield_s``, and goes on
    as soon as the predict ends; without a running predict it does not wait at all."""
    import threading
    import time

    busy = threading.Event()
    worker = FusionWorker(est, yield_to=busy, max_yield_s=0.15)
    t = time.perf_counter()
    worker._yield()
    assert time.perf_counter() - t < 0.05 and "fusion_deferred" not in est.stats.snapshot()["counts"]
    busy.set()
    t = time.perf_counter()
    worker._yield()  # the predict never ends: bounded
    assert 0.15 <= time.perf_counter() - t < 1.0
    worker.max_yield_s = 2.0
    threading.Timer(0.03, busy.clear).start()
    t = time.perf_counter()
    worker._yield()  # the predict ends after 30 ms: fusion goes on then, long before the bound
    assert 0.02 <= time.perf_counter() - t < 1.0
    assert est.stats.snapshot()["counts"]["fusion_deferred"] == 2
