"""The damping set on the training clips' longer predictions (calibrate.damping): a model whose
damping training left too low gets it back from clips the true damping made; the true one keeps it;
the report gives the value set and the range that fit tells."""

import math

import numpy as np
import pytest
import torch

from calibrate.damping import settle_damping
from calibrate.fit import Round, prediction_fit
from calibrate.identifiability import scaled
from calibrate.report import damping_set
from calibrate.tracks import Track
from deform import generate_recording, generic_model

from .conftest import LENGTH, MASS, N

FRAMES, EVERY_CLOUD, HORIZON = 200, 3, 150


def _points_along(x: np.ndarray, per_edge: int = 5) -> np.ndarray:
    """Points on the polyline ``x`` (n, 3): what a camera's rope points are to the fit."""
    s = np.linspace(0.0, 1.0, per_edge, endpoint=False)[None, :, None]
    return (x[:-1, None] + s * (x[1:, None] - x[:-1, None])).reshape(-1, 3)


def _track(model, seed: int) -> Track:
    """A clip of ``model``'s own motion, a cloud every 30 ms that shows the rope exactly."""
    truth = generate_recording(model, n_frames=FRAMES, seed=seed).positions
    steps = np.arange(0, FRAMES, EVERY_CLOUD)
    return Track(
        name=f"clip{seed}",
        positions=truth,
        grips=truth[:, [0, 1, -2, -1]],
        dt=model.dt,
        cloud_steps=steps,
        cloud_observed=np.ones((len(steps), N), dtype=bool),
        cloud_points=tuple(_points_along(truth[k]) for k in steps),
        status={},
    )


@pytest.fixture(scope="module")
def truth_and_tracks():
    torch.manual_seed(0)
    model = generic_model(LENGTH, MASS, N)
    with torch.no_grad():
        model.log_damping.fill_(math.log(2.0))  # 2/s: its effect builds up over the 1.5 s predicted
    return model, [_track(model, seed) for seed in range(3)]


def _fit(tracks):
    return lambda m: prediction_fit(m, tracks, HORIZON, 25)


@pytest.mark.slow
def test_a_damping_left_four_times_too_low_is_found_again(truth_and_tracks):
    truth, tracks = truth_and_tracks
    low = scaled(truth, "damping_per_s", 0.25)
    found, search = settle_damping(low, _fit(tracks))
    assert search["factor"] == pytest.approx(4.0, rel=0.2)  # within a quarter octave of the truth
    assert float(found.damping.detach()) == pytest.approx(2.0, rel=0.2)
    assert float(low.damping.detach()) == pytest.approx(0.5)  # the trained model is not changed
    assert search["fits"]["4"] < search["fits"]["1"]


@pytest.mark.slow
def test_the_true_damping_is_kept(truth_and_tracks):
    truth, tracks = truth_and_tracks
    found, search = settle_damping(truth, _fit(tracks))
    assert search["factor"] == 1.0 and found is truth


def test_clips_shorter_than_the_horizon_leave_the_damping_as_trained(truth_and_tracks):
    truth, tracks = truth_and_tracks
    found, search = settle_damping(truth, lambda m: prediction_fit(m, tracks, FRAMES, 25))
    assert found is truth and search["factor"] == 1.0 and search["fits"] == {}


def test_the_search_tells_the_range_its_fits_cannot_tell_apart():
    """A fit 1 % worse per half octave squared away from 0.2 /s: from 0.1 /s the search sets 0.2, and
    the nearest searched values that fit more than 1 % worse are one octave either side."""

    def fit(m):
        octaves = math.log2(float(m.damping.detach()) / 0.2)
        return 0.015 * (1.0 + 0.02 * octaves**2)

    model = generic_model(LENGTH, MASS, N)
    with torch.no_grad():
        model.log_damping.fill_(math.log(0.1))
    found, search = settle_damping(model, fit, tolerance=0.01)
    assert search["factor"] == pytest.approx(2.0) and float(found.damping.detach()) == pytest.approx(0.2)
    assert search["told_within_per_s"] == pytest.approx(
        [0.1, 0.4]
    )  # 0.5 octaves: 0.5 % worse, told apart at 1
    _, strict = settle_damping(model, fit, tolerance=0.004)
    assert strict["told_within_per_s"] == pytest.approx([0.2 * 2**-0.5, 0.2 * 2**0.5])


def test_the_report_gives_the_last_kept_rounds_search():
    search = {"factor": 2.0, "damping_per_s": [0.1, 0.2], "fits": {"1": 0.02, "2": 0.015},
              "told_within_per_s": [0.1, None], "horizon_s": 3.0}  # fmt: skip
    later = {
        "factor": 1.0,
        "damping_per_s": [0.2, 0.3],
        "fits": {"1": 0.01},
        "told_within_per_s": [None, None],
    }
    rounds = [
        Round(0, 0.02, 0.01, True, 1.0),
        Round(1, 0.015, 0.01, True, 1.0, {"damping": search}),
        Round(2, 0.0149, 0.01, False, 1.0, {"damping": later}),  # not kept: does not count
    ]
    assert damping_set(rounds) == {
        "trained_per_s": 0.1, "set_per_s": 0.2, "told_within_per_s": [0.1, None], "horizon_s": 3.0
    }  # fmt: skip
    assert damping_set(rounds[:1]) is None  # no round searched
