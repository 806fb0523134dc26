"""The loss-bias study (benchmarks/calibration_loss_bias.py): on a track that is the truth, seen
whole by a cloud at every step, all three losses agree and put the damping where it was."""

import numpy as np
import pytest

from benchmarks import calibration_loss_bias as study


def test_the_optimum_is_the_vertex_of_the_parabola_through_the_best_points():
    s = np.arange(-1.0, 1.25, 0.125)
    assert study.optimum(s, (s - 0.3) ** 2 + 1.0) == pytest.approx(0.3, abs=1e-9)
    assert study.optimum(s, -s) == s[-1]  # no minimum inside: the grid's best


def test_a_perfect_track_gives_the_truths_damping_under_every_loss(monkeypatch):
    from calibrate.tracks import Track
    from deform import DeformModel, generate_recording, gripped_indices, load_rod_config

    monkeypatch.setattr(study, "WINDOWS", 6)
    monkeypatch.setattr(study, "HORIZON", 30)
    model = DeformModel(load_rod_config("DLO2"))
    pairs = []
    for seed in range(2):
        x = generate_recording(model, n_frames=60, seed=seed).positions
        n = x.shape[1]
        observed = np.ones((len(x), n), bool)
        observed[:, gripped_indices(n)] = False
        grips = x[:, gripped_indices(n)]
        pairs.append((Track("t", x, grips, 0.01, np.arange(len(x)), observed, (), {}), x))
    losses = study.scan(model, pairs)
    np.testing.assert_allclose(losses["at the clouds"], np.array(losses["truth"]) * n / (n - 4), rtol=1e-9)
    best = {k: study.optimum(study.SCALES, np.array(v)) for k, v in losses.items()}
    assert abs(best["truth"]) < 0.1 and abs(best["smoothed track"] - best["truth"]) < 0.05
