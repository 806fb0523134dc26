"""Planted-effect generators produce what they claim, and the tool's terms can represent them."""

import math

import numpy as np
import pytest
import torch

from deform.diagnose.fitting import FitBudget, coarse_start, fit
from deform.diagnose.planted import generate_planted, oracle_term
from deform.diagnose.simulator import Nominal, Simulator, arclength_of
from deform.io.recordings import Recording
from deform.model import gripped_indices
from deform.terms.library import damping_modes, make_term

from .conftest import SPEC


def _planted(effect, sources):
    return generate_planted(
        effect, sources[:2], SPEC, n_frames=60, refine=2, substeps=2, settle_s=0.3, seed=3
    )


def test_delayed_rollout_moves_the_rod_ends_with_the_grips_of_earlier_frames(sources):
    recs, truth = _planted("actuation_delay", sources)
    term = oracle_term("actuation_delay", truth, SPEC.n_vertices, arclength_of(recs), 0.1)
    assert term.params()["delay_frames"] == pytest.approx(2.0)
    sim = Simulator(SPEC, Nominal(3e-3, 2e-3, 1.0), [term])
    sim.sync()
    X = torch.tensor(np.stack([r.positions[:20] for r in recs]))
    idx = gripped_indices(SPEC.n_vertices)
    plain = Simulator(SPEC, Nominal(3e-3, 2e-3, 1.0))
    plain.sync()
    with torch.no_grad():
        pred = sim.rollout(X, 6, margin=3)
        undelayed = plain.rollout(X, 6, margin=3)
    # step k predicts frame 3 + 2 + k: its gripped markers are that frame's recorded inputs (given,
    # not predicted), while the rod's ends followed the grips of frame 3 + k and moved the rest late
    assert torch.equal(pred[:, :, idx], X[:, 5:11][:, :, idx])
    free = [i for i in range(SPEC.n_vertices) if i not in idx]
    assert (pred[:, :, free] - undelayed[:, :, free]).abs().mean() > 1e-4


def test_marker_mass_truth_puts_mass_on_marker_nodes_only(sources):
    recs, truth = _planted("mass_scale", sources)
    ctrl, _ = _planted(None, sources)
    assert truth == {"marker_mass_kg": 0.004}
    # the extra mass changes the motion (same grips, same noise seed)
    assert np.abs(recs[0].positions - ctrl[0].positions).mean() > 1e-3


def test_drag_grid_trades_nominal_damping_for_drag(sources):
    recs, truth = _planted("aerodynamic_drag", sources)
    sim = Simulator(
        SPEC, Nominal(3e-3, 2e-3, 1.0), [make_term("aerodynamic_drag", SPEC.n_vertices, arclength_of(recs))]
    )
    term = sim.terms[0]
    out = coarse_start(sim, term, recs, FitBudget(batch=4, horizon=15))
    assert out["chosen"] is not None
    # the chosen quadratic coefficient is within a factor ~3.5 of the planted 3 /m
    assert abs(math.log(term.params()["quadratic_1_per_m"] / truth["quadratic_1_per_m"])) < math.log(3.5)


def _own_model_recordings(sources, name: str, setup) -> list[Recording]:
    """Recordings made by the tool's own model with the term ``name`` (set by ``setup``), so the
    truth is in the model class."""
    maker = Simulator(
        SPEC, Nominal(3e-3, 2e-3, 1.0), [make_term(name, SPEC.n_vertices, arclength_of(sources))]
    )
    with torch.no_grad():
        setup(maker.terms[0])
    starts = [Recording(r.name, r.positions[:60]) for r in sources[:3]]
    return [
        Recording(r.name, np.concatenate([r.positions[:2], p])) for r, p in zip(starts, maker.predict(starts))
    ]


def _fitted(name: str, recs, grid: bool) -> dict:
    sim = Simulator(SPEC, Nominal(3e-3, 2e-3, 1.0), [make_term(name, SPEC.n_vertices, arclength_of(recs))])
    term = sim.terms[0]
    if not grid:
        term.grid = list  # no starting points: the descent starts from the term's default
    fit(
        sim,
        recs,
        FitBudget(iterations=25, batch=6, horizon=15, progress=False),
        new_term=term,
        fit_nominal=False,
    )
    return term.params()


@pytest.mark.slow
def test_a_strong_wind_is_fitted_from_the_grid_within_the_quick_budget(sources):
    # a wind of 3.2 m/s^2 at 144 degrees: fitted in Cartesian components from no wind (tools before
    # v10), Adam's steps times the iterations capped the wind at about 0.75 m/s^2 per axis
    truth = np.array([-2.6, 1.9])
    recs = _own_model_recordings(sources, "external_force", lambda t: t.set_field(*truth))

    def wind(p):
        return np.array([p["ax_m_per_s2"], p["ay_m_per_s2"]])

    gridded = wind(_fitted("external_force", recs, grid=True))  # about (-2.53, 1.91)
    assert np.linalg.norm(gridded - truth) < 0.1 * np.linalg.norm(truth)
    plain = wind(_fitted("external_force", recs, grid=False))  # about (0.01, 0.09)
    assert np.linalg.norm(plain - truth) > 0.2 * np.linalg.norm(truth)


@pytest.mark.slow
def test_a_heavy_clip_is_fitted_from_the_grid_within_the_quick_budget(sources):
    # 25 g at 0.35 of the rope: fitted on a softplus of the mass (tools before v10), the fits
    # stopped at about 10.5 g; from the default start (2.5 g) the log alone does not get there
    def clip(t):
        t.raw_pos.fill_(math.log(0.35 / 0.65))
        t.log_mass.fill_(math.log(0.025))

    recs = _own_model_recordings(sources, "point_mass", clip)
    gridded = _fitted("point_mass", recs, grid=True)
    assert gridded["mass_kg"] == pytest.approx(0.025, rel=0.15)
    assert gridded["position_s"] == pytest.approx(0.35, abs=0.05)
    assert _fitted("point_mass", recs, grid=False)["mass_kg"] < 0.8 * 0.025


def _straight(lengths):
    l = torch.tensor([lengths], dtype=torch.float64)
    s = torch.cat([torch.zeros(1, 1, dtype=torch.float64), l.cumsum(-1)], -1)
    x = torch.zeros(1, l.shape[-1] + 1, 3, dtype=torch.float64)
    x[..., 0] = s
    return x, l, s


def test_internal_damping_ignores_rigid_motion_at_uneven_spacing_and_never_overshoots():
    x, l, s = _straight([0.03] + [0.095] * 9 + [0.03])  # short gripped end edges, as on the real rods
    term = make_term("internal_damping", 12, np.linspace(0, 1, 12))
    with torch.no_grad():
        term.log_nu.fill_(math.log(5.0))
        rigid = torch.zeros_like(x)
        rigid[..., 2] = 0.3 + 2.0 * s  # translation plus a turn of the grippers about y
        assert term.acceleration(x, rigid, None, l).abs().max() < 1e-9
        bend = torch.zeros_like(x)
        bend[..., 2] = torch.sin(math.pi * s / s[0, -1]) ** 2
        a = term.acceleration(x, bend, None, l)
        assert a.abs().max() > 0.1 and (a * bend).sum() < 0  # dissipates bending motion
        term.log_nu.fill_(math.log(1e6))  # dt nu lambda >> 1: an explicit step would reverse the modes
        v_next = bend + term.dt * term.acceleration(x, bend, None, l)
        # relative motion is removed, never reversed: the velocity ends up no larger than it was
        assert v_next.norm() <= bend.norm() + 1e-12


def test_internal_damping_modes_follow_each_recordings_rest_lengths():
    """The operator is cached per rest-length tensor: a new tensor (another recording) must get its
    own modes even when the allocator hands it the memory of a freed one (a cache keyed on the
    address returned the freed tensor's modes for most of these)."""
    term = make_term("internal_damping", 12, np.linspace(0, 1, 12))
    for i in range(30):
        rest = torch.full((1, 11), 0.09 + 0.001 * i, dtype=torch.float64)
        lam = term._modes(rest)[0].clone()
        del rest  # its memory is free for the next one
        again = damping_modes(torch.full((1, 11), 0.09 + 0.001 * i, dtype=torch.float64))[0]
        assert torch.allclose(lam, again)


def test_internal_damping_decomposes_its_operator_once_per_rollout_with_the_same_result(sources, monkeypatch):
    """The model hands terms a new batch-first view of its rest lengths every step: the cache must
    see through the view (it missed on every step, an eigendecomposition per step), and must still
    give what a fresh decomposition gives."""
    import deform.terms.library as terms_module

    X = torch.tensor(np.stack([r.positions[:22] for r in sources[:2]]))

    def rollout():
        term = make_term("internal_damping", SPEC.n_vertices, arclength_of(sources), {})
        with torch.no_grad():
            term.log_nu.fill_(math.log(20.0))
            sim = Simulator(SPEC, Nominal(3e-3, 2e-3, 0.5), [term])
            sim.sync()
            return sim.rollout(X, 20), term

    calls = []
    fresh = terms_module.damping_modes
    monkeypatch.setattr(terms_module, "damping_modes", lambda rest: calls.append(1) or fresh(rest))
    cached, _ = rollout()
    assert len(calls) == 1
    monkeypatch.setattr(terms_module.InternalDamping, "_modes", lambda self, rest: fresh(rest))
    assert torch.equal(cached, rollout()[0])


def test_internal_damping_means_the_same_on_a_finer_discretisation():
    """nu is a property of the rod: the decay rate of a smooth bending mode is the same on 12 and on
    34 vertices (the planted truth is the finer rod), unlike plain second differences of velocity."""
    rates = []
    for m in (11, 33):
        x, l, s = _straight([1.0 / m] * m)
        term = make_term("internal_damping", m + 1, np.linspace(0, 1, m + 1))
        v = torch.zeros_like(x)
        v[..., 2] = torch.sin(math.pi * s) ** 2  # smooth, zero with zero slope at both ends
        with torch.no_grad():
            a = term.acceleration(x, v, None, l)
        w = torch.cat([l[..., :1] / 2, (l[..., :-1] + l[..., 1:]) / 2, l[..., -1:] / 2], -1)
        rates.append(float(-(a * v).sum(-1).mul(w).sum() / v.pow(2).sum(-1).mul(w).sum()))
    # 0.84 measured (discretisation error of the coarse grid); plain second differences: a factor 81
    assert rates[0] > 0 and abs(rates[0] / rates[1] - 1) < 0.25


def test_windows_start_in_the_reference_frame_a_full_rollout_carries(sources):
    """A window cut from the middle of a recording starts with the directors transported in time
    from the first frame; a rest curvature acts in that frame. Fresh space-parallel directors differ
    by the accumulated holonomy of the motion."""
    from deform.rod import geometry as G
    from deform.rod.layout import batch_major, vertex_major

    def tangents(x):  # (T, n, 3) -> (T, n-1, 3)
        return torch.nn.functional.normalize(x[:, 1:] - x[:, :-1], dim=-1)

    P = np.asarray(sources[0].positions, dtype=np.float64)
    D = G.transported_frames(torch.tensor(P)).numpy()
    t = tangents(torch.tensor(P))
    assert (
        float((torch.tensor(D[1:]) * t[1:]).sum(-1).abs().max()) < 1e-9
    )  # perpendicular to the edges (frame 0 unused)
    # the same as what the model's own rollout carries when driven along the recorded positions
    model = Simulator(SPEC, Nominal()).model
    state = model.initial_state(torch.tensor(P[:1]), torch.tensor(P[1:2]))
    d1 = state.d1
    for k in range(2, 40):
        d1 = G.time_transport(
            vertex_major(d1, 2),
            vertex_major(tangents(torch.tensor(P[k - 1 : k])), 2),
            vertex_major(tangents(torch.tensor(P[k : k + 1])), 2),
        )
        d1 = batch_major(d1, (1,))
    assert torch.allclose(d1[0], torch.tensor(D[39]), atol=1e-9)
    fresh = batch_major(G.space_parallel_frame(vertex_major(t[60:61], 2)), (1,))[0]
    # the grippers have turned: fresh frames would start the window with a different material frame
    assert float((fresh - torch.tensor(D[60])).norm(dim=-1).max()) > 0.05


def test_the_truths_nodes_hold_the_noise_free_markers_where_a_hidden_node_simulator_puts_them(sources):
    nodes = []
    recs, _ = generate_planted(
        None,
        sources[:2],
        SPEC,
        n_frames=20,
        refine=3,
        substeps=2,
        settle_s=0.1,
        seed=3,
        noise_m=0.0,
        nodes_out=nodes,
    )
    every, ids = nodes
    assert every.shape == (2, 20, 3 * (SPEC.n_vertices - 3) + 3, 3)
    # the free markers are the truth's nodes (the gripped ones are the recorded inputs)
    markers = np.stack([r.positions for r in recs])
    assert np.array_equal(every[:, :, ids][:, :, 2:-2], markers[:, :, 2:-2])
    # a simulator with two hidden nodes per interval has its markers at the same nodes
    sim = Simulator(SPEC, Nominal(), hidden=2, substeps=2)
    assert sim.markers == ids and sim.n == every.shape[2] and sim.model.dt == SPEC.dt / 2
