"""Gripper poses interpolated between stamps (``service.geometry.interpolate_poses``, also what
calibration resamples bags with), and sampled one loop period a tick, whatever their arrival pattern."""

import numpy as np
import pytest

from service.geometry import interpolate_poses
from service.pose_timeline import NS, PoseTimeline
from tests.service.conftest import FakeClock, make_config

DT_NS = 10_000_000
T0 = 1_700_000_000 * NS


def _pose(t_ns: int) -> np.ndarray:
    """Two gripper poses moving at 0.2 m/s along x and turning about z at 1 rad/s (exact in time)."""
    s = (t_ns - T0) / NS
    out = np.zeros((2, 7))
    out[:, 0] = [-0.3 + 0.2 * s, 0.3 + 0.2 * s]
    out[:, 5], out[:, 6] = np.sin(s / 2), np.cos(s / 2)
    return out


def test_interpolation_halfway_and_on_the_short_arc():
    a, b = _pose(T0), _pose(T0 + DT_NS)
    stamps = np.array([T0, T0 + DT_NS])

    def at(p1, t):
        return interpolate_poses(stamps, np.stack([a, p1]), np.array([t]))[0]

    mid = at(b, T0 + DT_NS // 2)
    np.testing.assert_allclose(mid, _pose(T0 + DT_NS // 2), atol=1e-9)
    flipped = b.copy()
    flipped[:, 3:] *= -1  # the same orientation written with the other sign
    np.testing.assert_allclose(at(flipped, T0 + DT_NS // 2), mid, atol=1e-9)
    np.testing.assert_allclose(at(b, T0 + 3 * DT_NS), b)  # clamped


def test_poses_are_interpolated_between_stamps_whatever_the_quaternion_sign():
    stamps = np.array([0, 20_000_000])
    q = np.array([0.0, 0.0, np.sin(0.1), np.cos(0.1)])
    poses = np.zeros((2, 2, 7))
    poses[0, :, 3:] = q
    poses[1, :, 3:] = -q  # the same rotation
    poses[1, :, 0] = 0.02
    mid = interpolate_poses(stamps, poses, np.array([10_000_000]))[0]
    np.testing.assert_allclose(mid[:, 0], 0.01)
    np.testing.assert_allclose(np.abs(mid[:, 3:]), np.abs(q[None].repeat(2, 0)), atol=1e-12)


def _arrivals(seed: int, ticks: int):
    """Poses stamped every 8 ms (125 Hz) arriving in bursts: per 10 ms tick, 0 to 3 of them."""
    rng = np.random.default_rng(seed)
    k, out = 0, []
    for tick in range(ticks):
        due = T0 + (tick + 1) * DT_NS
        batch = []
        while T0 + k * 8_000_000 <= due and (rng.random() < 0.6 or not batch):
            batch.append(T0 + k * 8_000_000)
            k += 1
        out.append(batch)
    return out


def test_samples_advance_one_period_a_tick_and_lie_on_the_motion_whatever_the_arrivals():
    timeline = PoseTimeline(0.01)
    taus, newest, covered = [], [], 0
    for tick, batch in enumerate(_arrivals(0, 300)):
        for t in batch:
            timeline.add(t, _pose(t))
        [(tau, poses)] = timeline.next()
        taus.append(tau)
        newest.append(batch[-1] if batch else newest[-1])
        if tau <= newest[-1]:  # between two poses: on the motion
            np.testing.assert_allclose(poses, _pose(tau), atol=1e-6)
            covered += tick >= 100
    assert covered >= 0.9 * 200  # the delay keeps the samples behind the newest pose
    steps = np.diff(taus[100:]) / DT_NS
    assert np.abs(steps - 1).max() < 0.35  # even steps once following ...
    assert np.abs(np.diff(newest[100:]) / DT_NS - 1).max() >= 0.6  # ... where the newest pose jumps
    assert timeline.delay_ns() == pytest.approx(12_000_000)  # 1.5 intervals of 8 ms


def test_a_pause_longer_than_the_reset_is_jumped():
    timeline = PoseTimeline(0.01, delay_s=0.02)
    for k in range(20):
        timeline.add(T0 + k * DT_NS, _pose(T0 + k * DT_NS))
        timeline.next()
    later = T0 + 5 * NS
    timeline.add(later, _pose(later))
    [(tau, _)] = timeline.next()
    assert tau == later - 20_000_000


@pytest.mark.parametrize("interval_ns", [DT_NS, 1_000_000])
def test_samples_that_fell_half_a_second_behind_step_through_the_poses_missed(interval_ns):
    """A tick half a second late (the first tick's static solve, a stall): the next steps one period
    at a time up to where the samples should be, each on the motion (poses at 100 Hz and at 1 kHz:
    the half second's 500 are kept), then one a tick again."""
    timeline = PoseTimeline(0.01, delay_s=0.02)
    per_tick = DT_NS // interval_ns
    for k in range(3 * per_tick):
        timeline.add(T0 + k * interval_ns, _pose(T0 + k * interval_ns))
    [(first, _)] = timeline.next()
    for k in range(3 * per_tick, 53 * per_tick):  # 0.5 s of poses arrive while the loop is busy
        timeline.add(T0 + k * interval_ns, _pose(T0 + k * interval_ns))
    samples = timeline.next()
    taus = np.array([t for t, _ in samples])
    assert taus[-1] == T0 + k * interval_ns - 20_000_000  # the target, not beyond
    np.testing.assert_allclose(np.diff(np.r_[first, taus]) / DT_NS, 1.0, atol=0.05)
    for t, poses in samples:
        np.testing.assert_allclose(poses, _pose(t), atol=1e-6)
    timeline.add(T0 + (k + per_tick) * interval_ns, _pose(T0 + (k + per_tick) * interval_ns))
    assert len(timeline.next()) == 1


def test_a_wall_clock_estimator_steps_evenly_on_bursty_poses(model):
    """The history's pose times advance one period a tick (``pose_delay_s`` 12 ms), or repeat and
    jump (0, the default)."""
    from service import messages as M
    from service.estimator import Estimator
    from tests.service.open_loop_tracker import OpenLoopTracker

    steps = {}
    for delay in (0.012, 0.0):
        est = Estimator(make_config(pose_delay_s=delay), model, OpenLoopTracker(model, 5), clock=FakeClock())
        for tick, batch in enumerate(_arrivals(1, 120)):
            for t in batch:
                assert est.on_poses(M.pose_array(t, _pose(t)))
            est.tick(T0 + (tick + 1) * DT_NS)
        steps[delay] = np.diff([t.pose_ns for t in est.history])[60:] / DT_NS
        # the estimate is stamped with the time it describes (its poses'), not the tick's
        assert est.estimate.stamp_ns == est.history[-1].pose_ns
        if delay:
            assert est.estimate.stamp_ns < T0 + (tick + 1) * DT_NS - DT_NS
    assert np.abs(steps[0.012] - 1).max() < 0.35
    assert np.abs(steps[0.0] - 1).max() >= 0.6  # 0.8 and 1.6 periods: the gripper lurches


def test_the_message_grid_ticks_every_period_of_the_poses_own_time():
    """Poses at 125 Hz: one tick per 10 ms of their stamps, on the motion between them; poses on the
    grid are taken as they are; a gap beyond ``gap_s`` starts the grid again."""
    from service.pose_timeline import PoseGrid

    grid = PoseGrid(0.01)
    ticks = []
    for k in range(126):  # 1 s at 8 ms
        t = T0 + k * 8_000_000
        ticks += grid.add(t, _pose(t))
    times = np.array([t for t, _ in ticks])
    assert len(ticks) == 101 and times[0] == T0 and times[-1] == T0 + NS
    assert set(np.diff(times)) == {DT_NS}
    for t, p in ticks:
        np.testing.assert_allclose(p[:, :3], _pose(t)[:, :3], atol=1e-12)  # linear motion: exact
        np.testing.assert_allclose(p[:, 3:], _pose(t)[:, 3:], atol=1e-5)  # nlerp over 8 ms
    on_grid = PoseGrid(0.01)
    poses = [_pose(T0 + k * DT_NS) for k in range(3)]
    taken = [p for k in range(3) for _, p in on_grid.add(T0 + k * DT_NS, poses[k])]
    assert all(a is b for a, b in zip(taken, poses, strict=True))
    later = T0 + 2 * DT_NS + 3 * NS
    assert [t for t, _ in on_grid.add(later, _pose(later))] == [later]


def test_a_message_clock_estimator_replays_125_hz_poses_at_their_own_rate(model):
    """A bag with poses at 125 Hz: the model steps once per 10 ms of their stamps, and the rope after
    1.2 s is the one 100 Hz poses of the same motion give (one tick per message ran it 1.25x slow)."""
    from service import messages as M
    from service.estimator import Estimator
    from tests.service.open_loop_tracker import OpenLoopTracker

    def swing(t_ns: int) -> np.ndarray:
        s = (t_ns - T0) / NS
        out = np.zeros((2, 7))
        out[:, 0] = [-0.35, 0.35]
        out[:, 1] = 0.15 * np.sin(2 * np.pi * s)  # both grippers swing sideways at 1 Hz
        out[:, 2] = 0.5
        out[:, 5], out[:, 6] = 0.0, 1.0
        out[1, 5], out[1, 6] = 1.0, 0.0
        return out

    end = {}
    for period in (10_000_000, 8_000_000):
        est = Estimator(make_config(clock="message"), model, OpenLoopTracker(model, 20), clock=FakeClock())
        ticks, last = 0, None
        for k in range(int(1.2 * NS) // period + 1):
            t = T0 + k * period
            parsed = est.parse_poses(M.pose_array(t, swing(t)), last)
            last = t
            for tick_ns in est.set_poses(parsed):  # as the service's message loop ticks
                est.tick(tick_ns)
                ticks += 1
        assert ticks == 121 and est.estimate.stamp_ns == T0 + int(1.2 * NS)
        end[period] = est.estimate.x
    assert np.abs(end[8_000_000] - end[10_000_000]).max() < 1e-3


def test_a_late_first_tick_does_not_whip_the_rope(model, monkeypatch):
    """The first tick settles the rope (half a second); the poses sent meanwhile are stepped through
    at the next tick, so the model's rope moves as its grippers do. Jumped to in one step (as before),
    the grippers move 10 cm in 10 ms and the free rope flies off at metres a second."""
    from perception.tracker import Tracker
    from service import messages as M
    from service import pose_timeline, scenario
    from service.estimator import Estimator
    from service.geometry import poses_from_vertices

    positions, _ = scenario.demo_positions(120)
    grippers = scenario.offsets_for(positions)
    poses = poses_from_vertices(positions, grippers)
    cfg = make_config(pose_delay_s=0.02, grippers=grippers.model_dump())
    speed, counts, default = {}, {}, pose_timeline.CATCH_UP_S
    for catch_up_s in (default, 0.0):
        monkeypatch.setattr(pose_timeline, "CATCH_UP_S", catch_up_s)
        if not catch_up_s:  # the jump as it was: the rope not stopped after it either
            monkeypatch.setattr(Tracker, "hold_still", lambda self: None)
        est = Estimator(cfg, model, clock=FakeClock())
        for k in range(3):
            assert est.on_poses(M.pose_array(T0 + k * DT_NS, poses[k]))
        est.tick(T0 + 3 * DT_NS)  # initialises
        for k in range(3, 60):  # 0.57 s of motion arrive during the static solve
            assert est.on_poses(M.pose_array(T0 + k * DT_NS, poses[k]))
        est.tick(T0 + 60 * DT_NS)
        speed[catch_up_s] = float(est.tracker.state.v[0].norm(dim=-1).max())
        counts[catch_up_s] = est.stats.snapshot()["counts"].get("pose_catch_up_steps", 0)
    truth = np.linalg.norm(positions[57] - positions[56], axis=-1).max() / 0.01
    assert counts[default] >= 50 and counts[0.0] == 0
    assert speed[default] < 1.5 * truth  # measured: equal to the recording's 0.40 m/s
    assert speed[0.0] > 10 * speed[default]  # measured: 18.6 m/s


def test_a_jump_after_a_paused_sender_leaves_the_rope_at_rest(model, monkeypatch):
    """Poses stop for 3 s while the robot moves on: the next tick jumps the grippers there (too long
    a gap to step through) and stops the rope; kept, the jump's velocity throws it on."""
    from perception.tracker import Tracker
    from service import messages as M
    from service import scenario
    from service.estimator import Estimator
    from service.geometry import poses_from_vertices

    positions, _ = scenario.demo_positions(400)
    grippers = scenario.offsets_for(positions)
    poses = poses_from_vertices(positions, grippers)
    cfg = make_config(pose_delay_s=0.02, grippers=grippers.model_dump())
    speed, jumps = {}, {}
    for kept in (False, True):
        if kept:
            monkeypatch.setattr(Tracker, "hold_still", lambda self: None)
        est = Estimator(cfg, model, clock=FakeClock())
        for k in range(40):
            assert est.on_poses(M.pose_array(T0 + k * DT_NS, poses[k]))
            est.tick(T0 + (k + 1) * DT_NS)
        later = 340  # 3 s on
        for k in (later, later + 1):
            assert est.on_poses(M.pose_array(T0 + k * DT_NS, poses[k]))
        est.tick(T0 + (later + 2) * DT_NS)
        speed[kept] = float(est.tracker.state.v[0].norm(dim=-1).max())
        jumps[kept] = est.stats.snapshot()["counts"].get("pose_jumps", 0)
    assert np.abs(positions[later] - positions[39]).max() > 0.05  # the grippers moved on
    assert speed[False] == 0.0 and jumps[False] == 1
    assert speed[True] > 1.0  # m/s


def test_the_newest_pose_each_tick_stops_the_rope_after_a_late_first_tick(model):
    """``pose_delay_s: 0`` keeps no timeline to step through: the tick after the static solve jumps
    to the newest pose, and the rope is stopped after that step."""
    from service import messages as M
    from service import scenario
    from service.estimator import Estimator
    from service.geometry import poses_from_vertices

    positions, _ = scenario.demo_positions(120)
    grippers = scenario.offsets_for(positions)
    poses = poses_from_vertices(positions, grippers)
    est = Estimator(make_config(pose_delay_s=0.0, grippers=grippers.model_dump()), model, clock=FakeClock())
    assert est.on_poses(M.pose_array(T0, poses[0]))
    est.tick(T0 + DT_NS)  # initialises
    for k in range(1, 60):
        assert est.on_poses(M.pose_array(T0 + k * DT_NS, poses[k]))
    est.tick(T0 + 60 * DT_NS)
    assert float(est.tracker.state.v.abs().max()) == 0.0
    assert est.stats.snapshot()["counts"].get("pose_jumps") == 1
    for k in range(60, 70):  # then on as usual, one pose a tick
        assert est.on_poses(M.pose_array(T0 + k * DT_NS, poses[k]))
        est.tick(T0 + (k + 1) * DT_NS)
    assert est.stats.snapshot()["counts"].get("pose_jumps") == 1
    assert float(est.tracker.state.v.abs().max()) > 0.01


def test_the_message_clock_stops_the_rope_where_its_grid_starts_again(model):
    """A replay whose poses pause 3 s while the robot moves: the grid starts again at the later pose
    and the rope is stopped after that tick's step (as on the wall clock)."""
    from service import messages as M
    from service import scenario
    from service.estimator import Estimator
    from service.geometry import poses_from_vertices

    positions, _ = scenario.demo_positions(400)
    grippers = scenario.offsets_for(positions)
    poses = poses_from_vertices(positions, grippers)
    est = Estimator(make_config(clock="message", grippers=grippers.model_dump()), model, clock=FakeClock())
    last = None
    for k in [*range(40), 340]:
        parsed = est.parse_poses(M.pose_array(T0 + k * DT_NS, poses[k]), last)
        last = parsed[0]
        for t in est.set_poses(parsed):
            est.tick(t)
        if k == 39:
            assert float(est.tracker.state.v.abs().max()) > 0.01
    assert est.history[-1].pose_ns == T0 + 340 * DT_NS
    assert float(est.tracker.state.v.abs().max()) == 0.0
    assert est.stats.snapshot()["counts"].get("pose_jumps") == 1
