"""A strong planted effect is named; a control gives none; the report has the issue's schema."""

import pytest

from deform.diagnose.selection import diagnose

from .conftest import SPEC, planted_inputs, tiny_budget

CANDIDATES = ("external_force", "aerodynamic_drag", "point_mass")

pytestmark = pytest.mark.slow  # whole diagnoses on the tiny rod: about 25 s on two cores


@pytest.fixture(scope="module")
def wind(sources):
    inputs, truth = planted_inputs("external_force", sources)
    return diagnose(inputs, tiny_budget(CANDIDATES)), truth


def test_strong_wind_is_named_and_improves_the_check_error(wind):
    diag, _truth = wind
    rep = diag.report
    assert rep["selected"] == ["external_force"]
    # 0.92 with the wind fitted as strength and azimuth (tool v10), 0.87 with its components from no
    # wind; the tiny coarse model is far from its 2x finer truth, so the fitted wind is too (0.55, 0.56)
    assert rep["final_check_l1_m"] < 0.95 * rep["nominal"]["check_l1_m"]
    found = next(c for c in rep["candidates"] if c["name"] == "external_force")["params"]
    assert found["ax_m_per_s2"] > 0.4  # right direction (truth 1.6)


def test_report_has_the_issue_schema(wind):
    rep = wind[0].report
    assert set(rep) == {"nominal", "localization", "candidates", "selected", "final_check_l1_m"}
    assert {"params", "check_l1_m"} <= set(rep["nominal"])
    for c in rep["candidates"]:
        assert {"name", "params", "check_l1_m", "improvement", "significant"} <= set(c)
    assert rep["localization"]["findings"]


def test_control_gives_none(sources):
    inputs, _ = planted_inputs(None, sources)
    rep = diagnose(inputs, tiny_budget(CANDIDATES)).report
    assert rep["selected"] == []
    assert rep["final_check_l1_m"] == pytest.approx(rep["nominal"]["check_l1_m"])


def test_report_files_name_what_cannot_be_told_apart(wind, sources, tmp_path):
    from deform.diagnose.report import write_report

    diag, _ = wind
    inputs, _ = planted_inputs("external_force", sources)
    write_report(diag, inputs.check, tmp_path)
    md = (tmp_path / "report.md").read_text()
    assert (tmp_path / "report.json").is_file() and (tmp_path / "localization.png").is_file()
    assert "Selected: **external_force**" in md
    assert "What marker motion cannot tell apart" in md and "**mass_scale** from a stiffness scale" in md
    assert "fitted again on other windows" in md  # the selected term's own fit noise
    assert "named on its fitted size" not in md  # significant: named on its gain
    chosen = next(c for c in diag.report["candidates"] if c["name"] == "external_force")
    assert chosen["equivalence_class"][0] == "external_force" and "noise" in chosen["fit_noise"]


def test_slow_terms_grow_their_windows_against_their_own_reference(sources):
    """With ``grow_slow_terms`` the internal damping (a slow term) and a reference of its own are
    fitted on windows growing to the scoring windows; the other candidates keep the budget's
    windows and the common reference. A smoke-sized budget: the wiring, not the statistics."""
    import dataclasses

    from deform.diagnose.fitting import FitBudget
    from deform.diagnose.selection import DiagnoseBudget

    inputs, _ = planted_inputs(None, sources)
    b = DiagnoseBudget(
        nominal_iterations=3,
        candidate=FitBudget(iterations=3, batch=4, horizon=10, starts=1),
        max_rounds=1,
        candidates=("internal_damping", "external_force", "point_mass"),
        localization_recordings=3,
        progress=False,
    )
    out = {}
    for grow in (False, True):
        rep = diagnose(inputs, dataclasses.replace(b, grow_slow_terms=grow)).report
        out[grow] = {c["name"]: c for c in rep["candidates"]}
    assert not any(c["growing_windows"] for c in out[False].values())
    assert [n for n, c in out[True].items() if c["growing_windows"]] == ["internal_damping"]
    for name in ("external_force", "point_mass"):  # untouched by the option
        assert out[True][name]["improvement"] == out[False][name]["improvement"]
    ref = {n: c["reference_check_window_l1_m"] for n, c in out[True].items()}
    assert ref["external_force"] == ref["point_mass"]  # one common reference
    assert out[True]["internal_damping"]["improvement"] != out[False]["internal_damping"]["improvement"]


def test_slow_terms_are_fitted_with_the_finer_step_from_a_nominal_fit_of_their_own(sources):
    """With ``slow_step_s`` (the default) the internal damping and its reference run the model at
    that step (2 steps per frame here), in round 1 from a nominal model fitted at that step
    (``fine_nominal``); the other round-1 candidates at the 10 ms step from the 10 ms nominal fit,
    bit-identical to a run without the option. Smoke-sized: the wiring."""
    import dataclasses

    from deform.diagnose.fitting import FitBudget
    from deform.diagnose.selection import DiagnoseBudget

    inputs, _ = planted_inputs(None, sources)
    b = DiagnoseBudget(
        nominal_iterations=3,
        candidate=FitBudget(iterations=3, batch=4, horizon=10, starts=1),
        max_rounds=2,
        later_round_candidates=2,
        candidates=("internal_damping", "external_force", "point_mass"),
        localization_recordings=3,
        progress=False,
    )
    assert b.slow_step_s == pytest.approx(0.005) and b.fine_nominal
    rep = diagnose(inputs, b).report
    first = {c["name"]: c for c in rep["candidates"] if c["round"] == 1}
    assert first["internal_damping"]["model_step_s"] == pytest.approx(0.005)
    assert first["internal_damping"]["from_fine_nominal"]
    for name in ("external_force", "point_mass"):
        assert first[name]["model_step_s"] == pytest.approx(0.01) and not first[name]["from_fine_nominal"]
    fine = rep["nominal"]["fine"]
    assert fine["model_step_s"] == pytest.approx(0.005) and rep["nominal"]["model_step_s"] == pytest.approx(
        0.01
    )
    assert fine["params"] != rep["nominal"]["params"]  # fitted on its own
    coarse = diagnose(inputs, dataclasses.replace(b, slow_step_s=None)).report  # tool v10: all at 10 ms
    assert all(c["model_step_s"] == pytest.approx(0.01) for c in coarse["candidates"])
    assert coarse["nominal"]["fine"] is None
    # the other candidates and their common reference do not depend on the option (to rounding: the
    # 10 ms nominal fit is stepped in one batch with the fine one)
    old = {c["name"]: c for c in coarse["candidates"] if c["round"] == 1}
    for name in ("external_force", "point_mass"):
        assert first[name]["improvement"] == pytest.approx(old[name]["improvement"], rel=1e-9)


def test_later_rounds_keep_the_finer_step_once_a_slow_term_is_in():
    """``budget_for``'s rule, without a diagnosis: a slow term selected makes every term fine."""
    import numpy as np

    from deform.diagnose.selection import model_step_for
    from deform.terms.library import make_term

    s = np.linspace(0, 1, SPEC.n_vertices)
    damping, wind = (make_term(n, SPEC.n_vertices, s, {}) for n in ("internal_damping", "external_force"))
    assert model_step_for(wind, [], 0.0025) is None
    assert model_step_for(damping, [], 0.0025) == 0.0025
    assert model_step_for(wind, [damping], 0.0025) == 0.0025
    assert model_step_for(damping, [], None) is None
