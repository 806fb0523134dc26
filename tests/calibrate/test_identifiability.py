"""The range the held-out clips tell each parameter within (calibrate.identifiability)."""

import math

import pytest

from calibrate.identifiability import FACTORS, parameter_ranges, scaled, told_range
from deform import generic_model


def test_the_told_range_stops_at_the_first_factor_that_fits_worse():
    best = 1.0
    fits = {f: 1.0 + 0.02 * abs(math.log2(f)) for f in FACTORS}  # 2 % worse per doubling
    assert told_range(fits, best, 0.011) == (0.5, 2.0)  # the first factors more than 1.1 % worse
    fits[2**-0.25] = float("nan")  # a diverged rollout tells the value apart
    assert told_range(fits, best, 0.011)[0] == 2**-0.25
    flat = dict.fromkeys(FACTORS, 1.0)
    assert told_range(flat, best, 0.01) == (None, None)  # never left: not told on either side


def test_a_parameter_the_fit_does_not_see_is_reported_as_not_told():
    model = generic_model(1.0, 0.05, 10)
    ei = float(model.log_beta.detach().exp().median())

    def fit(m):  # only the bending stiffness matters; its best value is the model's
        return 0.01 * (1.0 + (float(m.log_beta.detach().exp().median()) / ei - 1.0) ** 2)

    out = parameter_ranges(model, fit, tolerance=0.01)
    bend = out["parameters"]["bend_stiffness_Nm2"]
    assert bend["told"] and bend["found"] == pytest.approx(ei)
    assert bend["told_within"] == pytest.approx([ei * 2**-0.25, ei * 2**0.25])  # |f - 1| > 0.1: told apart
    damping = out["parameters"]["damping_per_s"]
    assert not damping["told"] and damping["told_within"] == [None, None]
    assert scaled(model, "drag_per_m", 2.0).drag.item() == pytest.approx(2 * model.drag.item())
    assert model.drag.item() == pytest.approx(scaled(model, "drag_per_m", 1.0).drag.item())  # a copy


def test_nothing_is_claimed_without_a_held_out_fit():
    out = parameter_ranges(generic_model(1.0, 0.05, 10), lambda m: float("nan"), tolerance=0.01)
    assert out["parameters"] == {} and math.isnan(out["held_out_fit_m"])
