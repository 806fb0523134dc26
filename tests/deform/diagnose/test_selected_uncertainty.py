"""A selected term's uncertainty is measured on the final simulator's own copy of it: later rounds
fit copies of the terms chosen before them, so the chosen objects themselves are not in it."""

import copy
import math

import pytest
import torch

from deform.diagnose.fitting import FitBudget, laplace_uncertainty
from deform.diagnose.selection import selected_uncertainty
from deform.diagnose.simulator import Nominal, Simulator, arclength_of
from deform.terms.library import make_term

from .conftest import SPEC, WIND, planted_inputs

pytestmark = pytest.mark.slow  # loss evaluations on the tiny rod: a few seconds


def test_a_term_chosen_in_an_earlier_round_is_assessed_in_the_final_simulator(sources):
    inputs, _ = planted_inputs("external_force", sources)
    s = arclength_of(inputs.fit)
    wind = make_term("external_force", SPEC.n_vertices, s)
    with torch.no_grad():  # at the planted wind, where the loss curves
        wind.log_strength.fill_(math.log(math.hypot(WIND["ax_m_per_s2"], WIND["ay_m_per_s2"])))
        wind.azimuth.fill_(math.atan2(WIND["ay_m_per_s2"], WIND["ax_m_per_s2"]))
    drag = make_term("aerodynamic_drag", SPEC.n_vertices, s)
    final = Simulator(SPEC, Nominal(damping=0.2), [copy.deepcopy(wind), drag])  # round 2's fit
    budget = FitBudget(batch=6, horizon=15)
    wind_std, drag_std = selected_uncertainty(final, [wind, drag], inputs.fit, lambda t: budget)
    assert set(wind_std) == {"ax_m_per_s2", "ay_m_per_s2"} and set(drag_std) == set(drag.params())
    assert all(v is not None and 0 < v < 10.0 for v in wind_std.values()), wind_std
    # the chosen object itself moves nothing in the final simulator: no curvature, "undetermined"
    assert all(v is None for v in laplace_uncertainty(final, inputs.fit, budget, wind).values())
