"""Fits side by side in worker processes give the diagnosis that inline fits give."""

import dataclasses

import pytest

from deform.diagnose.pool import FitPool
from deform.diagnose.selection import diagnose

from .conftest import planted_inputs, tiny_budget

pytestmark = pytest.mark.slow  # two whole diagnoses on the tiny rod, one of them in two processes


def test_workers_give_the_same_names_and_numbers(sources):
    inputs, _ = planted_inputs("external_force", sources)
    # a slow term (its round-1 start is the nominal fit at the fine step, stepped with the 10 ms
    # one) and two rounds (the chosen term's refit on other windows runs through the pool too)
    # few iterations, no window growth: the two runs must agree, whatever they name
    tiny = tiny_budget(("external_force", "internal_damping"))
    budget = dataclasses.replace(
        tiny,
        max_rounds=2,
        nominal_iterations=8,
        grow_slow_terms=False,
        candidate=dataclasses.replace(tiny.candidate, iterations=8, batch=4, starts=1),
    )
    inline = diagnose(inputs, budget, workers=1).report
    pooled = diagnose(inputs, budget, workers=2).report
    assert inline["selected"] == pooled["selected"]
    assert inline["selected"], "nothing named: the refit through the pool was not exercised"
    assert inline["nominal"]["fine"] is not None
    assert pooled["nominal"]["fine"]["params"] == pytest.approx(inline["nominal"]["fine"]["params"], rel=1e-9)
    assert pooled["final_check_l1_m"] == pytest.approx(inline["final_check_l1_m"], rel=1e-9)
    assert [c["name"] for c in pooled["candidates"]] == [c["name"] for c in inline["candidates"]]
    for a, b in zip(inline["candidates"], pooled["candidates"]):
        assert b["improvement"] == pytest.approx(a["improvement"], rel=1e-9, abs=1e-12)
        assert b["params"] == pytest.approx(a["params"], rel=1e-9, abs=1e-12)
    named = inline["selected"][0]
    chosen = next(c for c in pooled["candidates"] if c["name"] == named)
    assert chosen["fit_noise"] == pytest.approx(
        next(c for c in inline["candidates"] if c["name"] == named)["fit_noise"], rel=1e-9
    )


def test_a_failing_fit_raises_in_the_caller():
    def boom(inputs=None):
        raise ValueError("bad fit")

    with FitPool(inputs=None, workers=1) as pool, pytest.raises(ValueError, match="bad fit"):
        pool.submit(boom).result()
