"""Cloud fusion off the loop: a cloud that arrives late is fused at the tick of its stamp, with the
ticks since replayed, so the estimate is the one fusing it in time would have given."""

import numpy as np
import pytest

from service.estimator import Estimator
from service.fusion import FusionWorker
from tests.service.conftest import FakeClock, make_config

T0 = 1_700_000_000 * 10**9
LATE_TICKS = 6  # 60 ms: a camera driver's latency and the decoding
LAST_CLOUD_TICK = 40  # clouds of later ticks are not sent: every cloud sent is fused in each run


def _run(model, stream, fuse_at: str, late: int) -> tuple[np.ndarray, np.ndarray]:
    """The stream's poses ticked at their stamps, each cloud fused (inline worker) ``late`` ticks
    after the tick of its stamp: the estimates (T, n, 3) and the model states the history keeps for
    clouds still to come (T, n, 3)."""
    # pose_delay_s 0: each tick steps to its own pose, so "the tick of a stamp" is that pose's tick
    cfg = make_config(camera={"fuse_at": fuse_at}, pose_delay_s=0)
    est = Estimator(cfg, model, clock=FakeClock())
    now = [0]
    est.wall_ns = lambda: now[0]  # the poses' clock: a cloud's age when fused is exact
    worker = FusionWorker(est)
    due: dict[int, list] = {}
    out = []
    for m in stream:
        if m.name == "camera_info":
            est.on_camera_info(m.data)
        elif m.name == "camera_pose":
            est.on_camera_pose(m.data)
        elif m.name == "points" and 0 < est.tick_index <= LAST_CLOUD_TICK:  # after the pose of its stamp
            cloud = est.decode_cloud(m.data)
            if late == 0:
                worker.fuse(cloud)
                out[-1] = est.tracker.x
            else:
                due.setdefault(est.tick_index + late, []).append(cloud)
        elif m.name == "ee_poses":
            assert est.on_poses(m.data)
            now[0] = m.log_time
            est.tick(m.log_time)
            for cloud in due.pop(est.tick_index, []):
                worker.fuse(cloud)
            out.append(est.tracker.x)
    assert not due
    kept = [t.moment.state.x[0].numpy() for t in est.history] if est.rewinds else []
    return np.array(out), np.array(kept), est.status()


@pytest.fixture(scope="module")
def runs(model, sim_stream):
    _, stream = sim_stream
    return {
        "in time": _run(model, stream, "stamp", 0),
        "late, at the stamp": _run(model, stream, "stamp", LATE_TICKS),
        "late, at arrival": _run(model, stream, "arrival", LATE_TICKS),
        "open loop": _run(model, [m for m in stream if m.name != "points"], "stamp", 0),
    }


def test_a_late_cloud_fused_at_its_stamp_gives_the_estimate_of_one_in_time(runs):
    (in_time, kept_in_time, _), (late, kept_late, status) = runs["in time"], runs["late, at the stamp"]
    after = slice(LAST_CLOUD_TICK + LATE_TICKS, None)
    np.testing.assert_allclose(late[after], in_time[after], rtol=0, atol=1e-9)
    assert np.abs(in_time[after] - runs["open loop"][0][after]).max() > 1e-3  # the clouds did correct it
    # every tick a later cloud could go back to holds what the clouds before it made of it
    np.testing.assert_allclose(kept_late, kept_in_time, rtol=0, atol=1e-9)
    assert status["cloud_age_ms"]["p50"] == status["cloud_age_ms"]["max"] == pytest.approx(10 * LATE_TICKS)


def test_a_late_cloud_fused_where_it_arrives_pulls_the_rope_back(runs):
    in_time, late = runs["in time"][0], runs["late, at arrival"][0]
    after = slice(LAST_CLOUD_TICK + LATE_TICKS, None)
    assert np.abs(late[after] - in_time[after]).max() > 1e-3


def test_a_cloud_newer_than_every_tick_waits_for_its_own(model, sim_stream):
    """Ticks step to poses ``pose_delay_s`` (20 ms) behind the newest, so a cloud taken with the
    newest pose is newer than every tick: not due until a tick reaches its stamp, then fused at
    that tick. One whose stamp no tick reaches (its camera's clock ahead) waits the pose delay and
    three periods of the fusion thread's clock, and is counted."""

    _, stream = sim_stream
    est = Estimator(make_config(pose_delay_s=0.02), model, clock=FakeClock())
    worker = FusionWorker(est)
    cloud, stamps = None, []
    for m in stream:
        if m.name == "camera_info":
            est.on_camera_info(m.data)
        elif m.name == "camera_pose":
            est.on_camera_pose(m.data)
        elif m.name == "points" and cloud is None and len(stamps) > 30:
            cloud = est.decode_cloud(m.data)
            assert cloud.stamp_ns == stamps[-1] and not worker.due(cloud)
        elif m.name == "ee_poses":
            assert est.on_poses(m.data)
            stamps.append(m.log_time)
            est.tick(m.log_time)
            if cloud is not None and worker.due(cloud):
                break
    assert abs(est.fusion_tick(cloud.stamp_ns).pose_ns - cloud.stamp_ns) <= 5_000_000  # its own tick
    assert abs(est.history[-1].pose_ns - cloud.stamp_ns) <= 5_000_000  # and the first to reach it
    ahead = type(cloud)(cloud.stamp_ns + 10**9, cloud.xyz, cloud.rgb, cloud.camera)
    worker.clock = worker_clock = FakeClock()
    worker.sleep = worker_clock.sleep
    worker._await_tick(ahead)
    assert worker.ahead_wait_s() == pytest.approx(0.05)
    assert worker_clock.t - 1000.0 == pytest.approx(0.05, abs=0.002)
    assert est.status()["counts"]["clouds_ahead_of_poses"] == 1


def test_a_tracker_that_cannot_be_copied_is_corrected_in_the_loop_thread(model):
    """The fallback: no copy to fuse in a worker, so the cloud corrects the tracker itself; it is
    counted, and its age recorded, as a fused cloud."""
    import threading

    from service import messages as M
    from tests.service.open_loop_tracker import OpenLoopTracker

    tracker = OpenLoopTracker(model, settle_steps=5)
    tracker.unpicklable = threading.Lock()
    est = Estimator(make_config(), model, tracker, clock=FakeClock())
    est.wall_ns = lambda: T0 + 40_000_000
    worker = FusionWorker(est)
    pose = np.array([[-0.4, 0, 0.5, 0, 0, 0, 1], [0.4, 0, 0.5, 0, 0, 1, 0]], dtype=float)
    assert est.on_poses(M.pose_array(T0, pose))
    est.tick(T0)
    est.on_camera_info(M.camera_info(T0, np.diag([100.0, 100, 1]), 4, 4))
    worker.fuse(
        est.decode_cloud(
            M.point_cloud(T0 + 10_000_000, np.ones((4, 4, 3), np.float32), np.zeros((4, 4, 3), np.uint8))
        )
    )
    assert not worker._can_clone and est.tracker is tracker
    status = est.status()
    assert status["counts"]["clouds_fused"] == 1
    assert status["cloud_age_ms"]["p50"] == pytest.approx(30.0)


def test_ticks_that_run_during_a_fusion_are_replayed_exactly(model, sim_stream):
    """The loop does not wait for a fusion: ticks come while the worker corrects. Once the fused
    tracker is swapped in, the estimate is the one an instant fusion gives, tick for tick."""
    _, stream = sim_stream

    def run(during: int) -> tuple[np.ndarray, int]:
        est = Estimator(make_config(), model, clock=FakeClock())
        worker = FusionWorker(est)
        poses = iter([m for m in stream if m.name == "ee_poses"])
        out = []

        def tick() -> None:
            m = next(poses)
            assert est.on_poses(m.data)
            est.tick(m.log_time)
            out.append(est.tracker.x)

        call = worker.worker.call

        def slow_call(*args, **kwargs):  # the loop ticks while the worker corrects
            result = call(*args, **kwargs)
            for _ in range(during):
                tick()
            return result

        worker.worker.call = slow_call
        clouds = [m for m in stream if m.name == "points"]
        for m in stream:
            if m.name == "camera_info":
                est.on_camera_info(m.data)
            elif m.name == "camera_pose":
                est.on_camera_pose(m.data)
        while len(out) < 55:
            tick()
            if len(out) % 4 == 0 and clouds:
                cloud = est.decode_cloud(clouds.pop(0).data) if est.tick_index > 8 else None
                if cloud is not None and worker.due(cloud):
                    worker.fuse(cloud)
                    out[-1] = est.tracker.x
        return np.array(out), est.status()["counts"].get("clouds_fused", 0)

    (instant, fused), (slow, fused_slow) = run(0), run(2)
    assert fused == fused_slow >= 5
    assert np.abs(instant[-1] - slow[-1]).max() < 1e-9
    assert np.abs(instant - slow).max() > 1e-4  # meanwhile the loop published the uncorrected rope
