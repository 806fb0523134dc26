"""Which tracked motion trains and which is held out (calibrate.fit.split); the time limit cuts
work short and says so (calibrate.fit.calibrate); the default vertex count follows the length."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from calibrate import fit, report
from calibrate.bags import read_clip
from calibrate.errors import CalibrationError
from calibrate.fit import Budget, Round, calibrate, default_vertices, projected_round_s, split
from calibrate.tracks import Track
from perception import PerceptionConfig
from service.config import ServiceConfig

from .conftest import LENGTH, MASS, N


def _track(name: str, frames: int) -> Track:
    steps = np.arange(0, frames, 10)
    return Track(
        name=name,
        positions=np.zeros((frames, 6, 3)),
        grips=np.zeros((frames, 4, 3)),
        dt=0.01,
        cloud_steps=steps,
        cloud_observed=np.zeros((len(steps), 6), dtype=bool),
        cloud_points=tuple(np.zeros((0, 3)) for _ in steps),
        status={},
    )


def _frames(tracks):
    return sum(t.n_frames for t in tracks)


def test_a_few_recordings_train_on_most_of_each_and_hold_out_their_ends():
    tracks = [_track("b", 3000), _track("a", 2000)]  # two 20-30 s bags
    train, held = split(tracks, every=5, min_frames=52)
    assert [t.name for t in held] == ["a[held out]", "b[held out]"]
    assert _frames(train) == 1400 + 2100 and _frames(held) == 600 + 900  # 70 %, not a whole bag
    assert held[0].cloud_steps.min() == 0 and held[0].cloud_steps.max() < 600  # re-based on the piece


def test_many_clips_hold_out_every_fifth_whole():
    tracks = [_track(f"clip{i}", 500) for i in range(10)]
    train, held = split(tracks, every=5, min_frames=52)
    assert [t.name for t in held] == ["clip0", "clip5"] and len(train) == 8
    assert all(t.n_frames == 500 for t in train + held)


def test_clips_too_short_to_cut_keep_one_whole_clip_back():
    tracks = [_track(f"clip{i}", 150) for i in range(3)]  # 30 % = 45 frames < the 52 scored
    train, held = split(tracks, every=5, min_frames=52)
    assert [t.name for t in held] == ["clip0"] and [t.name for t in train] == ["clip1", "clip2"]
    (one,) = split([_track("long", 1000)], every=5, min_frames=52)[1]  # a single recording: always cut
    assert one.name == "long[held out]" and one.n_frames == 300


def _calibrate(clips, budget: Budget):
    """The session's three clips calibrated with ``budget``, no progress bars."""
    cfg = ServiceConfig(grippers=clips.grippers)
    clip_list = [read_clip(b, cfg) for b in clips.bags]
    return calibrate(
        clip_list, LENGTH, MASS, cfg.grippers, PerceptionConfig(), n_vertices=N, budget=budget, progress=False
    )


def test_the_default_vertex_count_keeps_edges_near_9_cm_within_12_to_14():
    assert default_vertices(0.3) == 12  # a short rope keeps the shape resolution
    assert default_vertices(0.973) == 12  # 11 edges of 8.8 cm
    assert default_vertices(0.99) == 12  # exactly 11 edges of 9 cm: no float rounding up
    assert default_vertices(1.032) == 13  # DLO1 between its grippers
    assert default_vertices(5.0) == 14  # a long cable: training time caps it
    with pytest.raises(CalibrationError, match="positive"):
        default_vertices(0.0)


@pytest.mark.slow
def test_a_time_limit_cuts_training_short_skips_later_rounds_and_says_so(clips):
    """A limit already spent when training starts: round 1 trains one iteration of 50 (a model is
    still written, from what there was time for) and no later round runs; the notes say so."""
    budget = Budget(
        iterations=50, refine_iterations=2, rounds=2, horizon=20, batch=2, curriculum=(), time_limit_s=1e-6
    )
    cal = _calibrate(clips, budget)
    assert cal.model is not None
    assert [r.index for r in cal.rounds] == [0, 1]
    assert cal.rounds[1].cut_by_time_limit and cal.rounds[1].train["iterations"] == 1
    assert "round 1 trained 1 of 50 iterations" in cal.time_limit_notes[0]
    if cal.rounds[1].kept:  # a kept round would have been followed by round 2, had there been time
        assert "round 2 not started" in cal.time_limit_notes[1]
    # no more held-out clips than the ranges' least: they tell the parameters past the limit too
    assert len(cal.held_out_names) <= fit.RANGE_TRACKS
    assert cal.parameter_ranges["held_out_clips"] == cal.held_out_names and cal.parameter_ranges["parameters"]


def test_a_later_round_is_projected_from_the_last_ones_training_and_the_rest_of_it():
    """500 iterations trained in 500 s of a 650 s round: 200 take 200 s, 240 with the spare, and the
    150 s of damping search, tracking and scoring come again whole."""
    previous = Round(1, 0.01, 0.005, True, seconds=650.0, train={"iterations": 500}, train_s=500.0)
    assert projected_round_s(previous, iterations=200) == pytest.approx(1.2 * 200 + 150)


@pytest.mark.slow  # a whole calibration: tens of seconds
def test_training_leaves_time_for_the_rest_of_its_round(clips, monkeypatch):
    """With 1000 s left at every round's start, round 1 trains for at most 1000 s less the estimate
    of its rest (first_round_rest_s) and the reserve, round 2 less what round 1 did besides
    training (its damping search, tracking and scoring), each rest with 20 % to spare, so that the
    round ends within the limit."""
    monkeypatch.setattr(fit, "MIN_GAIN", -1.0)  # every round kept
    monkeypatch.setattr(fit, "_time_left", lambda *a: 1000.0)
    monkeypatch.setattr(fit, "first_round_rest_s", lambda *a: 100.0)
    limits = []
    train = fit._train

    def recording_train(*args):
        limits.append(args[-1])
        return train(*args)

    monkeypatch.setattr(fit, "_train", recording_train)
    budget = Budget(
        iterations=3, refine_iterations=2, rounds=2, horizon=20, batch=2, curriculum=(), damping_horizon=40
    )
    cal = _calibrate(clips, budget)
    _, r1, r2 = cal.rounds
    assert 0.0 < r1.train_s < r1.seconds and 0.0 < r2.train_s < r2.seconds
    assert limits == pytest.approx(
        [1000.0 - 1.2 * 100.0 - fit.RESERVE_S, 1000.0 - 1.2 * (r1.seconds - r1.train_s) - fit.RESERVE_S]
    )


def test_round_ones_rest_is_round_zeros_pass_slowed_by_the_network_and_the_damping_search(monkeypatch):
    """One rollout timed without the residual network (2 s) and one with it (3 s): round 0's 80 s
    tracking pass becomes 120 s, and the damping search's 11 rollouts 33 s; no search, no 33 s."""
    fits, clock = [], [0.0]

    def timed_fit(model, tracks, horizon, every, workers=None):
        fits.append((model.options.residual, horizon))
        clock[0] += 3.0 if model.options.residual else 2.0
        return 0.0

    monkeypatch.setattr(fit, "prediction_fit", timed_fit)
    monkeypatch.setattr(fit, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    model = fit.start_model(LENGTH, MASS, np.full(N - 1, LENGTH / (N - 1)), "rope")
    round0 = Round(0, 0.01, 0.005, True, seconds=80.0)
    tracks = [_track("a", 500)]
    assert fit.first_round_rest_s(round0, model, tracks, Budget(damping_horizon=300)) == 120.0 + 11 * 3.0
    assert fits == [(False, 300), (True, 300)] and not model.options.residual  # copies were switched
    assert fit.first_round_rest_s(round0, model, tracks, Budget(damping_horizon=0)) == 120.0


@pytest.mark.slow
def test_the_damping_search_rolls_out_a_bounded_spread_of_the_training_tracks(clips, monkeypatch):
    """Many clips: the damping search (and round 1's time probe of it) rolls out at most
    DAMPING_TRACKS of the training tracks, spread from the first to the last; few: all of them."""
    tracks = [_track(f"clip{i}", 500) for i in range(44)]  # 280 s of clips less the held-out fifth
    picked = fit.damping_tracks(tracks)
    assert len(picked) == fit.DAMPING_TRACKS and picked[0] is tracks[0] and picked[-1] is tracks[-1]
    assert len({t.name for t in picked}) == fit.DAMPING_TRACKS
    assert fit.damping_tracks(tracks[:8]) == tracks[:8]  # 50 s of clips: as before
    monkeypatch.setattr(fit, "DAMPING_TRACKS", 1)
    seen, prediction_fit = [], fit.prediction_fit

    def counting_fit(model, tracks, horizon, every, workers=None):
        seen.append((horizon, len(tracks)))
        return prediction_fit(model, tracks, horizon, every, workers=workers)

    monkeypatch.setattr(fit, "prediction_fit", counting_fit)
    budget = Budget(iterations=1, rounds=1, horizon=20, batch=2, curriculum=(), damping_horizon=40)
    cal = _calibrate(clips, budget)
    assert len(cal.train_names) > 1
    assert {n for h, n in seen if h == 40} == {1}  # the probe and every fit of the search: one track


def test_the_work_after_the_rounds_is_reserved_as_long_as_its_held_out_fits_take():
    """The parameter ranges repeat the held-out fit FITS times: 5 s fits keep 1.2 x 31 x 5 s; quick
    fits keep the fixed reserve."""
    assert fit.RANGE_FITS == 31
    slow = Round(1, 0.01, 0.005, True, seconds=900.0, held_fit_s=5.0)
    assert fit.end_reserve_s(slow) == pytest.approx(1.2 * 31 * 5.0)
    assert fit.end_reserve_s(Round(1, 0.01, 0.005, True, seconds=900.0, held_fit_s=0.1)) == fit.RESERVE_S


def test_the_parameter_ranges_use_the_held_out_tracks_the_time_left_affords():
    """12 held-out clips whose fit takes 2.8 s: the ranges' 31 fits of all of them want 104 s with
    the spare. 48 s left (10 kept for the report): 4 clips, spread from the first to the last; plenty
    or no limit: all 12; nothing left: still RANGE_TRACKS, the least that tells a value."""
    tracks = [_track(f"clip{i}", 500) for i in range(12)]
    picked = fit.ranges_tracks(tracks, 2.8, 48.0)
    assert len(picked) == 4 and picked[0] is tracks[0] and picked[-1] is tracks[-1]
    assert 1.2 * 31 * 2.8 * 4 / 12 <= 48.0 - fit.REPORT_S < 1.2 * 31 * 2.8 * 5 / 12
    assert fit.ranges_tracks(tracks, 2.8, 1000.0) == tracks
    assert fit.ranges_tracks(tracks, 2.8, None) == tracks
    assert fit.ranges_tracks(tracks, 0.0, 48.0) == tracks  # not timed (no limit when round 0 ran)
    assert len(fit.ranges_tracks(tracks, 2.8, -5.0)) == fit.RANGE_TRACKS
    long_first = [_track("long", 5000)] + tracks[1:]  # by frames, not by count: the long clip is dear
    assert len(fit.ranges_tracks(long_first, 2.8, 48.0)) < 4


@pytest.mark.slow
def test_a_round_that_would_pass_the_time_limit_is_not_started(clips, monkeypatch, tmp_path):
    """Every round kept (MIN_GAIN below any change) and round 2 projected to take longer than the
    limit leaves: round 1 trains its whole budget, round 2 never starts, and the note says so."""
    monkeypatch.setattr(fit, "MIN_GAIN", -1.0)
    monkeypatch.setattr(fit, "projected_round_s", lambda *a: 1e9)
    budget = Budget(
        iterations=3,
        refine_iterations=2,
        rounds=3,
        horizon=20,
        batch=2,
        curriculum=(),
        time_limit_s=1e6,
        damping_horizon=40,
    )
    cal = _calibrate(clips, budget)
    assert [r.index for r in cal.rounds] == [0, 1] and cal.rounds[1].kept
    search = cal.rounds[1].train["damping"]  # the damping was set on the training clips' 0.4 s predictions
    assert len(search["fits"]) >= 9
    assert float(cal.model.damping.detach()) == pytest.approx(search["damping_per_s"][1], rel=1e-6)
    inputs = {"length_m": LENGTH, "mass_kg": MASS, "vertices": N, "out": "rope.pt", "bags": []}
    out = report.write(cal, [], inputs, tmp_path)  # the report says where the damping came from
    assert json.loads((out / "report.json").read_text())["identified"]["damping_set"][
        "set_per_s"
    ] == pytest.approx(search["damping_per_s"][1])
    assert "by the training clips' 0.4 s predictions" in (out / "report.md").read_text()
    assert cal.rounds[1].train["iterations"] == 3 and not cal.rounds[1].cut_by_time_limit
    assert (
        cal.time_limit_notes == [cal.time_limit_notes[0]]
        and "rounds 2..3 not started" in cal.time_limit_notes[0]
    )
    assert cal.parameter_ranges["held_out_clips"] == cal.held_out_names  # time for all of them
    assert json.loads((out / "report.json").read_text())["identified"]["told_by_clips"] == cal.held_out_names
