"""Recordings at other frame rates than the DEFORM dataset's 100 Hz (the frame period is ROD.json's)."""

import json

import numpy as np
import pytest
import torch

from deform.diagnose.resample import TOOL_DT, resample
from deform.diagnose.simulator import MAX_STEP_S, Nominal, Simulator, frame_substeps
from deform.diagnose.spec import load_inputs
from deform.io import save_recording
from deform.io.recordings import Recording

from .conftest import SPEC


def test_frame_substeps_keep_every_model_step_within_the_longest_step():
    assert MAX_STEP_S == 0.01
    assert [frame_substeps(dt) for dt in (0.005, 0.01, 0.02, 1 / 60, 1 / 30)] == [1, 1, 2, 2, 4]
    sim = Simulator(SPEC.model_copy(update={"dt": 1 / 30}), Nominal())
    assert sim.substeps == 4 and sim.model.dt == pytest.approx(1 / 120)
    assert Simulator(SPEC.model_copy(update={"dt": 0.02}), Nominal(), hidden=1).substeps == 4


def test_a_rod_stepped_at_50_hz_follows_its_100_hz_motion(sources):
    # the 100 Hz motion of the tool's own model, seen at 50 Hz: one explicit 20 ms step per frame
    # left it by 1.2 cm (5.8 cm of motion), two 10 ms substeps with the grippers interpolated
    # between frames follow it within 1 mm
    ei = 2e-3
    X = torch.tensor(np.stack([r.positions[:62] for r in sources[:3]]))
    sim = Simulator(SPEC, Nominal(ei, 0.7 * ei, 0.5))
    sim.sync()
    with torch.no_grad():
        truth = torch.cat([X[:, :2], sim.rollout(X, 60)], 1)
    frames50 = truth[:, ::2]
    sim50 = Simulator(SPEC.model_copy(update={"dt": 0.02}), Nominal(ei, 0.7 * ei, 0.5))
    assert sim50.substeps == 2
    sim50.sync()
    with torch.no_grad():
        pred = sim50.rollout(frames50, frames50.shape[1] - 2)
    err = (pred - frames50[:, 2:]).abs().mean()
    motion = (frames50[:, 2:] - frames50[:, 1:2]).abs().mean()  # how far the rod moves meanwhile
    assert err < 0.05 * motion, (float(err), float(motion))


def test_recordings_at_another_rate_are_resampled_to_100_hz_by_the_rod_files_period(tmp_path, sources):
    for name, recs in (("fit", sources[:2]), ("check", sources[2:3])):
        (tmp_path / name).mkdir()
        for i, r in enumerate(recs):
            save_recording(tmp_path / name / f"{i:02d}.pkl", r.positions[::2])  # 50 Hz
    rod = tmp_path / "rod.json"
    rod.write_text(json.dumps({**SPEC.model_dump(), "dt": 0.02}))
    inputs = load_inputs(rod, tmp_path / "fit", tmp_path / "check")
    assert inputs.spec.dt == TOOL_DT and {r.dt for r in inputs.fit + inputs.check} == {TOOL_DT}
    assert any("resampled to the tool's 100 Hz" in w for w in inputs.warnings)
    original, back = sources[0].positions, inputs.fit[0].positions
    assert len(back) == (len(original) - 1) // 2 * 2 + 1
    np.testing.assert_allclose(back[::2], original[: len(back) : 2], atol=1e-12)  # the frames given
    # between them the spline follows the 100 Hz motion far closer than a straight line does
    spline_err = np.abs(back[1::2] - original[1 : len(back) : 2]).mean()
    linear_err = np.abs((back[:-2:2] + back[2::2]) / 2 - original[1 : len(back) : 2]).mean()
    assert spline_err < 0.5 * linear_err, (spline_err, linear_err)


@pytest.mark.parametrize("rate_hz", [30.0, 240.0])
def test_resampling_follows_a_smooth_motion_from_slower_and_faster_rates(rate_hz):
    def motion(t):  # 1.5 Hz, 2 cm: a rope swinging under a gripper
        return 0.02 * np.sin(2 * np.pi * 1.5 * t)[:, None, None] * np.ones((1, 4, 3))

    dt = 1 / rate_hz
    rec = Recording(name="r", positions=motion(np.arange(round(2.0 / dt) + 1) * dt), dt=dt)
    out = resample(rec, dt)
    t = np.arange(out.n_frames) * TOOL_DT
    assert out.dt == TOOL_DT and abs(t[-1] - 2.0) < 1e-9
    err = np.abs(out.positions - motion(t)).max()
    assert err < 1e-3 * 0.02, err
