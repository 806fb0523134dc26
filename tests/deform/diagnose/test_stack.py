"""Models stepped as one batch give each model's numbers alone (deform.diagnose.stack)."""

import copy
import dataclasses
import random

import numpy as np
import pytest
import torch

from deform.diagnose.checked_fit import CheckErrors
from deform.diagnose.fitting import (
    FitBudget,
    _descend,
    apply_point,
    fit,
    forward_loss,
    make_windows,
    rank_starts,
)
from deform.diagnose.joint_fit import descend_together, fit_together
from deform.diagnose.simulator import Nominal, Simulator
from deform.diagnose.stack import Stack, groups_of
from deform.io.recordings import arclength_of
from deform.terms.library import make_term

from .conftest import SPEC, planted_inputs

# a term of every kind of hook: an acceleration, a mass, a bound stiffness, shifted grips
NAMES = [None, "aerodynamic_drag", "point_mass", "stiffness_variation", "actuation_delay", "ground_contact"]


def _sims(recs, names=NAMES):
    s = arclength_of(recs)
    ctx = {"lowest_z": min(float(r.positions[:, 2:-2, 2].min()) for r in recs), "peak_s": 0.4}
    out = []
    for k, name in enumerate(names):
        terms = [] if name is None else [make_term(name, SPEC.n_vertices, s, ctx)]
        out.append(Simulator(SPEC, Nominal(damping=0.2 + 0.1 * k), terms))
    with torch.no_grad():  # move every term off its defaults, so that a mix-up between models shows
        for k, sim in enumerate(out):
            for p in sim.term_parameters():
                p.add_(0.05 * (k + 1))
    return out


def _rollouts_alone_and_stacked(alone, stacked, X, steps, margin, d1, origin):
    """Each of ``alone``'s rollouts on its own, and ``stacked``'s as one :class:`Stack`."""
    with torch.no_grad():
        own = []
        for sim in alone:
            sim.sync()
            own.append(sim.rollout(X, steps, margin, d1=d1, origin=origin))
        together, _ = Stack(stacked).rollout(X, steps, margin, d1=d1, origin=origin)
    return own, together


def _assert_descents_as_alone(alone, stacked, recordings, budget):
    """``alone`` descended one by one and ``stacked`` (the same models) together end alike."""
    out_alone = [_descend(sim, recordings, budget, "alone", True) for sim in alone]
    out_stacked = descend_together(stacked, recordings, budget, "stacked")
    for a, b, oa, ob in zip(alone, stacked, out_alone, out_stacked, strict=True):
        np.testing.assert_allclose(ob["loss_history_m"], oa["loss_history_m"], rtol=1e-6)
        for pa, pb in zip(a.parameters(), b.parameters(), strict=True):
            torch.testing.assert_close(pb.detach(), pa.detach(), rtol=1e-5, atol=1e-7)


@pytest.fixture(scope="module")
def recordings(sources):
    inputs, _ = planted_inputs("point_mass", sources)
    return inputs.fit


def test_a_stacked_rollout_is_each_models_own(recordings):
    sims = _sims(recordings)
    X, d1, origin = make_windows(recordings, 5, 15, 3, random.Random(0))
    alone, stacked = _rollouts_alone_and_stacked(sims, sims, X, 15, 3, d1, origin)
    for a, b in zip(alone, stacked, strict=True):
        assert torch.isfinite(a).all()
        assert (a - b).abs().max() < 1e-12
    # the models differ by more than that: the comparison would see a swapped model
    assert (alone[0] - alone[1]).abs().max() > 1e-5


def test_stacked_descents_are_each_models_own(recordings):
    budget = FitBudget(iterations=4, batch=4, horizon=12, progress=False)
    alone, stacked = _sims(recordings), _sims(recordings)
    _assert_descents_as_alone(alone, stacked, recordings, budget)


def test_fit_together_keeps_the_start_fit_keeps(recordings):
    """Several starts per term (the first of them the term's own values) and a reference, as a
    selection round fits them."""
    budget = FitBudget(iterations=3, batch=4, horizon=12, progress=False, starts=2)
    names = [None, "point_mass", "aerodynamic_drag"]

    def sims():
        out = _sims(recordings, names)
        # the point mass starts at its grid's best point, which then ranks first as "the term's
        # own values" (point None) beside the grid's points
        pm = out[1]
        apply_point(pm, pm.terms[0], rank_starts(pm, pm.terms[0], recordings, budget)[0][1])
        return out

    alone = sims()
    outs = [fit(sim, recordings, budget, new_term=sim.terms[0] if sim.terms else None) for sim in alone]
    together = fit_together([(s, s.terms[0] if s.terms else None) for s in sims()], recordings, budget, "x")
    for sim, out, (tsim, tout) in zip(alone, outs, together, strict=True):
        assert ("starts" in out) == ("starts" in tout)
        if "starts" in out:
            assert [s["point"] for s in tout["starts"]] == [s["point"] for s in out["starts"]]
            np.testing.assert_allclose(
                [s["loss_m"] for s in tout["starts"]], [s["loss_m"] for s in out["starts"]], rtol=1e-6
            )
        for pa, pb in zip(sim.parameters(), tsim.parameters(), strict=True):
            torch.testing.assert_close(pb.detach(), pa.detach(), rtol=1e-5, atol=1e-7)
    # the case of a start at the term's own values (point None) beside a grid point is exercised
    assert any(s["point"] is None for out in outs for s in out.get("starts", []))


def test_groups_are_few_even_and_in_order():
    assert groups_of([]) == []
    assert groups_of([1, 2, 2], most=12) == [[0, 1, 2]]
    groups = groups_of([1] + [2] * 9, most=12)  # 19 models: two groups of about 10
    assert [i for g in groups for i in g] == list(range(10))
    assert len(groups) == 2
    sizes = [sum(([1] + [2] * 9)[i] for i in g) for g in groups]
    assert max(sizes) <= 12 and min(sizes) >= 8
    assert groups_of([20, 1], most=12) == [[0], [1]]  # an item larger than a group stands alone


def test_a_fitted_rest_curvature_stacked_with_others_is_each_models_own(recordings):
    """A model fitting a rest curvature takes the iterative twist solve, the others the closed form,
    in one batch (the rest curvature model listed between the others)."""
    names = [None, "rest_curvature", "aerodynamic_drag"]
    budget = FitBudget(iterations=3, batch=4, horizon=12, progress=False)
    alone, stacked = _sims(recordings, names), _sims(recordings, names)
    _assert_descents_as_alone(alone, stacked, recordings, budget)
    # forward: the fitted curvature is not zero, so its model is solved iteratively there too
    assert stacked[1].terms[0].params() != _sims(recordings, names)[1].terms[0].params()
    X, d1, origin = make_windows(recordings, 3, 10, 3, random.Random(1))
    own, together = _rollouts_alone_and_stacked(stacked, stacked, X, 10, 3, d1, origin)
    for a, b in zip(own, together, strict=True):
        assert (a - b).abs().max() < 1e-12
    assert (own[0] - own[1]).abs().max() > 1e-6


def test_models_at_other_model_steps_stacked_are_each_models_own(recordings):
    """A model stepped at half the step of another (the tool's two nominal fits) keeps its state on
    the ticks between its steps, and takes its own step length and grips."""

    def sims():
        coarse = Simulator(SPEC, Nominal(damping=0.3))
        fine = Simulator(SPEC, Nominal(damping=0.4), max_step_s=SPEC.dt / 2)
        return [coarse, fine, Simulator(SPEC, Nominal(damping=0.5))]

    alone, stacked = sims(), sims()
    assert [s.substeps for s in alone] == [1, 2, 1]
    X, d1, origin = make_windows(recordings, 3, 12, 3, random.Random(2))
    own, together = _rollouts_alone_and_stacked(alone, stacked, X, 12, 3, d1, origin)
    for a, b in zip(own, together, strict=True):
        assert (a - b).abs().max() < 1e-12
    assert (own[0] - own[1]).abs().max() > 1e-6
    budget = FitBudget(iterations=3, batch=4, horizon=10, progress=False)
    _assert_descents_as_alone(alone, stacked, recordings, budget)


def test_stacked_simulators_must_share_their_frames_and_divide_the_finest_step(recordings):
    a = Simulator(SPEC, Nominal(), max_step_s=SPEC.dt / 2)
    b = Simulator(SPEC, Nominal(), max_step_s=SPEC.dt / 3)
    with pytest.raises(ValueError, match="divide"):
        Stack([a, b])
    with pytest.raises(ValueError, match="hidden"):
        Stack([a, Simulator(SPEC, Nominal(), hidden=1)])


def test_check_errors_of_a_batch_are_each_models_own(sources, recordings):
    inputs, _ = planted_inputs("point_mass", sources)
    sims = _sims(recordings)
    together = CheckErrors.of_all(sims, inputs.check)
    for sim, c in zip(sims, together, strict=True):
        alone = CheckErrors.of(sim, inputs.check)
        np.testing.assert_allclose(c.rollout, alone.rollout, rtol=1e-10)
        np.testing.assert_allclose(c.window, alone.window, rtol=1e-10)
    assert abs(together[0].window.mean() - together[1].window.mean()) > 1e-6  # the models differ


def test_grid_ranking_scores_each_point_as_alone(recordings):
    budget = FitBudget(batch=4, horizon=12, progress=False)
    sim = _sims(recordings, ["ground_contact"])[0]
    term = sim.terms[0]
    ranked = rank_starts(sim, term, recordings, budget)
    assert len(ranked) == 1 + len(term.grid())
    windows = make_windows(
        recordings, budget.batch, budget.horizon, budget.margin, random.Random(budget.seed + 1)
    )
    for loss, point in ranked[:3] + ranked[-2:]:
        c = copy.deepcopy(sim)
        apply_point(c, c.terms[0], point)
        assert forward_loss(c, windows, budget) == pytest.approx(loss, rel=1e-10)
    assert [lp[0] for lp in ranked] == sorted(lp[0] for lp in ranked)


def test_a_refit_on_windows_of_its_own_stacked_with_other_fits_is_its_own(sources):
    """The chosen candidate's refit (another start, windows of another seed) stepped with the next
    round's fits ends as when fitted alone."""
    from deform.diagnose.checked_fit import fit_and_check_together

    inputs, _ = planted_inputs("point_mass", sources)
    s = arclength_of(inputs.fit)
    budget = FitBudget(iterations=3, batch=4, horizon=10, progress=False, starts=2)
    seed = budget.seed + 101
    group_start, own_start = Nominal(damping=0.3), Nominal(damping=0.6)

    def term(name):
        return make_term(name, SPEC.n_vertices, s, {"peak_s": 0.4})

    refit = [([], None, own_start, seed), ([term("point_mass")], 0, own_start, seed)]
    together = fit_and_check_together(
        SPEC, group_start, [([term("aerodynamic_drag")], 0), *refit], inputs, budget, "together"
    )
    alone = fit_and_check_together(
        SPEC, own_start, [m[:2] for m in refit], inputs, dataclasses.replace(budget, seed=seed), "alone"
    )
    for (asim, ac), (tsim, tc) in zip(alone, together[1:], strict=True):
        np.testing.assert_allclose(tc.window, ac.window, rtol=1e-6)
        for pa, pb in zip(asim.parameters(), tsim.parameters(), strict=True):
            torch.testing.assert_close(pb.detach(), pa.detach(), rtol=1e-5, atol=1e-7)
    # the other seed's windows matter: the same refit on the group's windows ends elsewhere
    same_windows = fit_and_check_together(SPEC, own_start, [m[:2] for m in refit], inputs, budget, "x")
    assert np.abs(same_windows[0][1].window - alone[0][1].window).max() > 1e-6
