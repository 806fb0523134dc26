"""Planted-effect generators produce what they claim, and the tool's terms can represent them."""
import math

import numpy as np
import pytest
import torch

from deform.diagnose.fitting import FitBudget, coarse_start
from deform.diagnose.planted import generate_planted, oracle_term
from deform.diagnose.simulator import Nominal, Simulator, arclength_of
from deform.diagnose.terms import make_term
from deform.model import gripped_indices

from .conftest import SPEC


def _planted(effect, sources):
    return generate_planted(effect, sources[:2], SPEC, n_frames=60, refine=2, substeps=2, settle_s=0.3, seed=3)


def test_delayed_rollout_moves_the_rod_ends_with_the_grips_of_earlier_frames(sources):
    recs, truth = _planted("actuation_delay", sources)
    term = oracle_term("actuation_delay", truth, SPEC.n_vertices, arclength_of(recs), 0.1)
    assert term.params()["delay_frames"] == pytest.approx(2.0)
    sim = Simulator(SPEC, Nominal(3e-3, 2e-3, 1.0), [term])
    sim.sync()
    X = torch.tensor(np.stack([r.positions[:20] for r in recs]))
    idx = gripped_indices(SPEC.n_vertices)
    with torch.no_grad():
        pred = sim.rollout(X, 6, margin=3)
    # step k predicts frame 3 + 2 + k; its gripped vertices are the recorded grips of frame 3 + k
    assert torch.allclose(pred[:, :, idx], X[:, 3:9][:, :, idx])


def test_marker_mass_truth_puts_mass_on_marker_nodes_only(sources):
    recs, truth = _planted("mass_scale", sources)
    ctrl, _ = _planted(None, sources)
    assert truth == {"marker_mass_kg": 0.004}
    # the extra mass changes the motion (same grips, same noise seed)
    assert np.abs(recs[0].positions - ctrl[0].positions).mean() > 1e-3


def test_drag_grid_trades_nominal_damping_for_drag(sources):
    recs, truth = _planted("aerodynamic_drag", sources)
    sim = Simulator(SPEC, Nominal(3e-3, 2e-3, 1.0), [make_term("aerodynamic_drag", SPEC.n_vertices, arclength_of(recs))])
    term = sim.terms[0]
    out = coarse_start(sim, term, recs, FitBudget(batch=4, horizon=15))
    assert out["chosen"] is not None
    # the chosen quadratic coefficient is within a factor ~3.5 of the planted 3 /m
    assert abs(math.log(term.params()["quadratic_1_per_m"] / truth["quadratic_1_per_m"])) < math.log(3.5)


def test_internal_damping_is_rayleigh_for_slow_modes_and_never_overshoots():
    n = 10
    term = make_term("internal_damping", n, np.linspace(0, 1, n))
    v = torch.randn(2, n, 3, dtype=torch.float64)
    d2 = v[:, :-2] - 2 * v[:, 1:-1] + v[:, 2:]
    explicit = torch.zeros_like(v)
    explicit[:, :-2] += d2
    explicit[:, 1:-1] -= 2 * d2
    explicit[:, 2:] += d2
    with torch.no_grad():
        term.log_eta.fill_(math.log(1e-3))
        a = term.acceleration(None, v, None, None)
        assert torch.allclose(a, -1e-3 * explicit, rtol=1e-3, atol=1e-6)
        term.log_eta.fill_(math.log(1e3))  # dt eta lambda >> 1: an explicit step would reverse the modes
        v_next = v + term.dt * term.acceleration(None, v, None, None)
        # damping only removes energy of relative motion: no mode grows or flips sign
        modal0 = torch.einsum("ij,bjk->bik", term.Q.T, v)
        modal1 = torch.einsum("ij,bjk->bik", term.Q.T, v_next)
        assert torch.all(modal1 * modal0 >= -1e-12) and torch.all(modal1.abs() <= modal0.abs() + 1e-12)
