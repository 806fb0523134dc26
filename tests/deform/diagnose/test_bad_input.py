"""Bad inputs: one clear error naming the file (exit code 2, nothing written) or a report warning."""

import json

import numpy as np
import pytest

from deform.cli import main
from deform.diagnose.spec import load_inputs
from deform.io import save_recording
from deform.io.recordings import RecordingError


def _write(tmp_path, n_fit=3, n_check=2, n=8, length=0.6, check_n=None, nan=0, dt=0.01):
    """``nan``: frames (from frame 10) the first check recording loses marker 3 for."""
    rng = np.random.default_rng(0)
    fit, check = tmp_path / "fit", tmp_path / "check"
    fit.mkdir()
    check.mkdir()
    base = np.zeros((50, n, 3))
    base[:, :, 0] = np.linspace(0, 0.6, n)
    for i in range(n_fit):
        save_recording(fit / f"{i}.pkl", base + rng.normal(0, 1e-3, base.shape))
    cn = check_n or n
    cbase = np.zeros((50, cn, 3))
    cbase[:, :, 0] = np.linspace(0, 0.6, cn)
    for i in range(n_check):
        x = cbase + rng.normal(0, 1e-3, cbase.shape)
        if nan and i == 0:
            x[10 : 10 + nan, 3, 2] = np.nan
        save_recording(check / f"{i}.pkl", x)
    rod = tmp_path / "rod.json"
    rod.write_text(json.dumps({"length_m": length, "mass_kg": 0.04, "n_vertices": n, "dt": dt}))
    return rod, fit, check


def _cli(rod, fit, check, out, *extra):
    return main(
        ["diagnose", "--rod", str(rod), "--fit", str(fit), "--check", str(check), "--out", str(out), *extra]
    )


def _budgets_asked(monkeypatch, tmp_path, *option_lists) -> list:
    """The DiagnoseBudget ``deform diagnose`` builds for each list of extra options (stopped before
    any fitting)."""
    import deform.diagnose.selection as selection

    rod, fit, check = _write(tmp_path)
    used = []

    def fake_diagnose(inputs, budget, start_model=None, workers=1):
        used.append(budget)
        raise SystemExit(0)

    monkeypatch.setattr(selection, "diagnose", fake_diagnose)
    for extra in option_lists:
        with pytest.raises(SystemExit):
            _cli(rod, fit, check, tmp_path / "out", *extra)
    return used


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"check_n": 9}, "markers"),
        ({"nan": 20}, "marker 3 is missing for 20 frames from frame 10"),  # 0.2 s: not filled
        ({"n_fit": 1}, "at least"),
        ({"length": 0.5}, "length_m"),  # a rope shorter than its markers' span
        ({"length": 2.0}, "span only 0.6"),  # markers over 30 % of the rope: not the rope simulated
        ({"length": 600.0}, "ROD.json in millimetres?"),
        ({"length": 0.0006}, "recordings in millimetres?"),
        ({"dt": 0.005}, "shorter than 40 frames at 100 Hz"),  # 50 frames at 200 Hz: 0.25 s
    ],
)
def test_bad_input_is_one_error_line_and_nothing_written(tmp_path, capsys, kwargs, needle):
    rod, fit, check = _write(tmp_path, **kwargs)
    out = tmp_path / "out"
    assert _cli(rod, fit, check, out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and "error" in err[0]
    assert not out.exists()


def test_a_short_dropout_is_filled_and_said_and_max_gap_bounds_it(tmp_path, capsys):
    rod, fit, check = _write(tmp_path, nan=5)
    inputs = load_inputs(rod, fit, check)
    assert not any(np.isnan(r.positions).any() for r in inputs.fit + inputs.check)
    assert any("5 marker-frame(s) filled" in w for w in inputs.warnings)
    with pytest.raises(RecordingError, match="missing for 5 frames"):
        load_inputs(rod, fit, check, max_gap_s=0.04)
    out = tmp_path / "out"
    assert _cli(rod, fit, check, out, "--max-gap", "0") == 2
    assert "marker 3 is missing for 5 frames" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:  # a bad number stops at parsing
        _cli(rod, fit, check, out, "--max-gap", "-1")
    assert stop.value.code == 2 and "--max-gap" in capsys.readouterr().err
    assert not out.exists()


def test_swapped_marker_labels_are_restored_and_said(tmp_path):
    from deform.io import load_recording

    rod, fit, check = _write(tmp_path)
    x = load_recording(check / "1.pkl").positions
    swapped = x.copy()
    swapped[10:20, [3, 4]] = x[10:20, [4, 3]]
    save_recording(check / "1.pkl", swapped)
    inputs = load_inputs(rod, fit, check, smooth_noise=False)  # 1 mm of noise would be smoothed
    assert np.array_equal(inputs.check[1].positions, x)
    assert any("markers 3-4: 10 frame(s)" in w for w in inputs.warnings)


def test_bad_rod_json_names_the_file(tmp_path, capsys):
    rod, fit, check = _write(tmp_path)
    rod.write_text('{"length_m": -1}')
    assert _cli(rod, fit, check, tmp_path / "out") == 2
    assert str(rod) in capsys.readouterr().err


def test_length_off_by_a_little_is_a_warning(tmp_path):
    rod, fit, check = _write(tmp_path, length=0.57)  # 5 % shorter than the 0.6 m the markers span
    inputs = load_inputs(rod, fit, check)
    assert any("length" in w for w in inputs.warnings)
    assert inputs.spec.length_m == 0.57


@pytest.mark.parametrize("length", [0.64, 0.8, 1.15])
def test_a_rope_longer_than_its_markers_is_simulated_over_the_span(tmp_path, length):
    """Real ropes run past their outer markers: the span is simulated with its share of the mass."""
    rod, fit, check = _write(tmp_path, length=length)
    inputs = load_inputs(rod, fit, check)
    span = inputs.spec.length_m
    assert span == pytest.approx(0.6, abs=0.01)
    assert inputs.spec.mass_kg == pytest.approx(0.04 * span / length)
    assert any("past its markers" in w for w in inputs.warnings)


def test_two_check_recordings_warn_about_the_interval(tmp_path):
    rod, fit, check = _write(tmp_path)
    assert any("bootstrap" in w for w in load_inputs(rod, fit, check).warnings)


def test_budget_option_picks_the_budget(tmp_path, monkeypatch):
    from deform.diagnose.selection import DiagnoseBudget

    used = _budgets_asked(monkeypatch, tmp_path, ["--budget", "quick"], ["--budget", "full"])
    assert used[0] == DiagnoseBudget.quick() and used[1] == DiagnoseBudget()
    assert used[0].candidate.iterations < used[1].candidate.iterations
    rod, fit, check = tmp_path / "rod.json", tmp_path / "fit", tmp_path / "check"
    with pytest.raises(SystemExit) as bad:
        _cli(rod, fit, check, tmp_path / "out", "--budget", "huge")
    assert bad.value.code == 2


@pytest.mark.parametrize("value", ["-0.01", "0.5", "nan", "jaws"])
def test_a_bad_clamp_is_one_error_line_and_nothing_written(tmp_path, capsys, value):
    """The clamp ends before the next marker: 0 to half the marker spacing (0.043 m here), or fit."""
    rod, fit, check = _write(tmp_path)
    out = tmp_path / "out"
    assert _cli(rod, fit, check, out, "--clamp", value) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--clamp" in err[0] and "error" in err[0]
    assert not out.exists()


def test_a_given_clamp_is_held_and_fit_is_the_default(tmp_path, monkeypatch):
    options = ([], ["--clamp", "fit"], ["--clamp", "0.02"], ["--clamp", "0"])
    used = _budgets_asked(monkeypatch, tmp_path, *options)
    assert [(b.fit_clamp, b.clamp_m) for b in used] == [(True, 0.0), (True, 0.0), (False, 0.02), (False, 0.0)]


def _hanging(tmp_path, up="z"):
    """Recordings of a rope hanging 10 cm between grippers, exported z up or y up."""
    rng = np.random.default_rng(1)
    s = np.linspace(0, 1, 8)
    for d in ("fit", "check"):
        (tmp_path / d).mkdir(parents=True)
        for i in range(3):
            x = np.zeros((50, 8, 3))
            x[:, :, 0] = 0.6 * s
            x[:, :, 2] = 0.3 - 0.1 * np.sin(np.pi * s)
            if up == "y":
                x = x[..., [0, 2, 1]] * [1, 1, -1]  # y up: height in y, z toward the viewer
            if up == "arch":
                x[:, :, 2] = 0.3 + 0.1 * np.sin(np.pi * s)  # bowing upward, gravity still along -z
            save_recording(tmp_path / d / f"{i}.pkl", x + rng.normal(0, 3e-4, x.shape))
    rod = tmp_path / "rod.json"
    rod.write_text(json.dumps({"length_m": 0.7, "mass_kg": 0.04, "n_vertices": 8}))
    return rod, tmp_path / "fit", tmp_path / "check"


def test_a_rope_hanging_sideways_is_refused_and_one_bowing_up_is_a_warning(tmp_path, capsys):
    from deform.io.orientation import mean_sag

    rod, fit, check = _hanging(tmp_path / "z")
    inputs = load_inputs(rod, fit, check)
    assert mean_sag(inputs.fit)[2] < -0.03
    rod, fit, check = _hanging(tmp_path / "y", up="y")
    out = tmp_path / "out"
    assert _cli(rod, fit, check, out) == 2
    err = capsys.readouterr().err
    assert "hangs along -y" in err and "z up" in err and not out.exists()
    rod, fit, check = _hanging(tmp_path / "arch", up="arch")  # an arch is a warning only
    assert any("bows upward" in w for w in load_inputs(rod, fit, check).warnings)
