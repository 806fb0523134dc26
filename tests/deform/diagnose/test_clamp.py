"""The clamp past the gripped markers: a nominal parameter the grip carries, found from marker motion."""

import dataclasses

import pytest
import torch

from deform.diagnose.fitting import fit
from deform.diagnose.simulator import Nominal, Simulator, clamped
from deform.io.recordings import Recording

from .conftest import SPEC, tiny_budget


def test_clamp_moves_the_inner_grips_along_the_gripper_axis():
    grip = torch.tensor([[0.0, 0, 0], [0.03, 0, 0], [0.5, 0.1, 0], [0.5, 0.14, 0]], dtype=torch.float64)
    out = clamped(grip, torch.tensor(0.02, dtype=torch.float64))
    assert torch.equal(out[[0, 3]], grip[[0, 3]])
    assert torch.allclose(out[1], torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64))
    assert torch.allclose(out[2], torch.tensor([0.5, 0.08, 0.0], dtype=torch.float64))
    assert torch.equal(clamped(grip, torch.tensor(0.0, dtype=torch.float64)), grip)


def _recordings_with_clamp(sources, clamp_m: float) -> list[Recording]:
    truth = Simulator(SPEC, Nominal(2e-3, 1.4e-3, 0.5, clamp_m=clamp_m))
    return [
        Recording(name=f"clamp_{i}", positions=p, dt=r.dt)
        for i, (p, r) in enumerate(zip(truth.predict(sources), sources))
    ]


@pytest.mark.parametrize("clamp_m", [0.0, 0.025])
def test_nominal_fit_finds_the_clamp_length(sources, clamp_m):
    """From a clamp of 0 (a model freeing the rope at its marker), the nominal fit moves to the clamp
    the recordings were made with; on recordings freed at the marker it stays near 0."""
    recs = _recordings_with_clamp(sources, clamp_m)
    budget = dataclasses.replace(tiny_budget([]).candidate, iterations=40)
    sim = Simulator(SPEC, Nominal(2e-3, 1.4e-3, 0.5))
    fit(sim, recs, budget)
    assert sim.nominal.params()["clamp_m"] == pytest.approx(clamp_m, abs=0.004)


def test_a_given_clamp_is_held_by_the_fit(sources):
    """``--clamp METRES``: a gripper geometry the user knows stays where it is given, even where the
    recordings were made with another clamp, while EI and the damping are still fitted."""
    recs = _recordings_with_clamp(sources, 0.025)
    budget = dataclasses.replace(tiny_budget([]).candidate, iterations=10)
    nominal = Nominal(2e-3, 1.4e-3, 0.5)
    nominal.set_clamp(0.01, fitted=False)
    sim = Simulator(SPEC, nominal)
    ei = nominal.params()["bend_stiffness_Nm2"]
    fit(sim, recs, budget)
    assert sim.nominal.params()["clamp_m"] == pytest.approx(0.01, abs=1e-12)
    assert sim.nominal.params()["bend_stiffness_Nm2"] != ei


@pytest.mark.slow
def test_a_nominal_fit_ending_at_the_clamp_bound_is_restarted_and_the_better_end_kept(sources, monkeypatch):
    """A second start from a longer clamp runs when the first ends under CLAMP_RESTART_M (forced
    here by raising it), and the simulator keeps the second end only when it scores lower on the
    held-out fit windows by more than RESTART_MIN_GAIN; without a restart clamp there is no second
    start."""
    import deform.diagnose.fitting as fitting

    recs = _recordings_with_clamp(sources, 0.0)
    budget = dataclasses.replace(tiny_budget([]).candidate, iterations=15)
    held_out = fitting.held_out_windows(recs, budget)

    sim = Simulator(SPEC, Nominal())
    assert "clamp_restart" not in fitting.fit_nominal(sim, recs, budget, None)

    monkeypatch.setattr(fitting, "CLAMP_RESTART_M", 1.0)
    sim = Simulator(SPEC, Nominal())
    info = fitting.fit_nominal(sim, recs, budget, 0.02)["clamp_restart"]
    losses = info["held_out_loss_m"]
    assert info["clamp_start_m"] == 0.02 and losses["clamp_0"] != losses["clamp_restart"]
    better = losses["clamp_restart"] < (1 - fitting.RESTART_MIN_GAIN) * losses["clamp_0"]
    assert info["kept"] == ("clamp_restart" if better else "clamp_0")
    with torch.no_grad():
        now = fitting.forward_loss(sim, held_out, budget)
    assert now == pytest.approx(losses[info["kept"]], rel=1e-9)

    # without a margin the lower end is kept, whichever it is
    monkeypatch.setattr(fitting, "RESTART_MIN_GAIN", 0.0)
    sim = Simulator(SPEC, Nominal())
    info = fitting.fit_nominal(sim, recs, budget, 0.02)["clamp_restart"]
    with torch.no_grad():
        now = fitting.forward_loss(sim, held_out, budget)
    assert now == pytest.approx(min(info["held_out_loss_m"].values()), rel=1e-9)


@pytest.mark.slow
def test_nominal_fits_at_two_model_steps_together_end_as_alone(sources, monkeypatch):
    """The tool's two nominal fits (the candidates' model step and the slow terms' finer one) are
    stepped as one batch, restarts included: each ends where it ends alone."""
    import deform.diagnose.fitting as fitting
    from deform.diagnose.joint_fit import fit_nominals_together

    recs = _recordings_with_clamp(sources, 0.0)
    budget = dataclasses.replace(tiny_budget([]).candidate, iterations=6)
    monkeypatch.setattr(fitting, "CLAMP_RESTART_M", 1.0)  # both restart

    def sims():
        return [Simulator(SPEC, Nominal()), Simulator(SPEC, Nominal(), max_step_s=SPEC.dt / 2)]

    alone = sims()
    outs = [fitting.fit_nominal(sim, recs, budget, 0.02) for sim in alone]
    together = sims()
    touts = fit_nominals_together(together, recs, budget, 0.02)
    for sim, out, tsim, tout in zip(alone, outs, together, touts, strict=True):
        assert tout["coarse"] == out["coarse"]
        assert tout["clamp_restart"]["kept"] == out["clamp_restart"]["kept"]
        for k, v in out["clamp_restart"]["held_out_loss_m"].items():
            assert tout["clamp_restart"]["held_out_loss_m"][k] == pytest.approx(v, rel=1e-6)
        for pa, pb in zip(sim.parameters(), tsim.parameters(), strict=True):
            torch.testing.assert_close(pb.detach(), pa.detach(), rtol=1e-5, atol=1e-7)
    assert outs[0]["coarse"] != outs[1]["coarse"] or alone[0].nominal.params() != alone[1].nominal.params()
