"""Identifiability in the report: explanations the held-out data cannot tell apart are named together,
and localisation's contact height is among the contact term's starting points."""

import numpy as np

from deform.diagnose.selection import contact_height, equivalence_class
from deform.terms.library import make_term


def test_equally_good_explanations_form_one_class_and_a_worse_one_does_not():
    rng = np.random.default_rng(0)
    e_ref = np.full(6, 1.0)
    e_win = 0.7 + 0.02 * rng.standard_normal(6)
    twin = e_win + 0.02 * rng.standard_normal(6)  # the same fit up to noise
    worse = e_win + 0.15  # 15 % of the reference worse on every recording
    out = equivalence_class("a", e_win, e_ref, [("twin", twin), ("worse", worse)])
    assert out["equivalence_class"] == ["a", "twin"]
    assert len(out["equivalence_why"]) == 1 and "twin" in out["equivalence_why"][0]


def test_contact_grid_starts_at_the_localised_height():
    s = np.linspace(0, 1, 8)
    loc = {"by_height": {"low_threshold": 0.16, "low_vs_rest_ratio": 2.7}}
    assert contact_height(loc) == 0.16
    assert contact_height({"by_height": {"low_threshold": 0.16, "low_vs_rest_ratio": 1.1}}) is None
    term = make_term("ground_contact", 8, s, {"lowest_z": 0.10, "contact_z": contact_height(loc)})
    heights = {round(float(term.h0) + 0.02 * p["raw_h"], 4) for p in term.grid()}
    assert 0.16 in heights and round(0.10 + 0.002, 4) in heights
    plain = make_term("ground_contact", 8, s, {"lowest_z": 0.10})
    assert 0.16 not in {round(float(plain.h0) + 0.02 * p["raw_h"], 4) for p in plain.grid()}


def test_parameter_spread_is_none_where_the_fit_windows_do_not_determine_it(sources):
    """Laplace 1-sigma: finite for a wind the motion feels; None (report: "not determined") for a
    table far below the rope, whose height, stiffness and friction leave the loss flat, instead of
    the e^10-wide number a capped log step gave."""
    from deform.diagnose.fitting import FitBudget, laplace_uncertainty
    from deform.diagnose.simulator import Nominal, Simulator, arclength_of

    from .conftest import SPEC

    s = arclength_of(sources)
    budget = FitBudget(iterations=1, batch=6, horizon=15)
    table = make_term("ground_contact", SPEC.n_vertices, s, {"lowest_z": -5.0})
    std = laplace_uncertainty(Simulator(SPEC, Nominal(), [table]), sources, budget, table)
    assert set(std) == set(table.params()) and all(v is None for v in std.values())
    wind = make_term("external_force", SPEC.n_vertices, s, {})
    wind.set_field(1.0, 0.5)  # a wind's direction is felt only at some strength (its raw is polar)
    std = laplace_uncertainty(Simulator(SPEC, Nominal(), [wind]), sources, budget, wind)
    assert all(v is not None and 0 < v < 9.81 for v in std.values()), std  # (an unfitted model: wide)
