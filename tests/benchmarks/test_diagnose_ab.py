"""The A/B summary of two checkouts' diagnoses: speed-up as base over head, names compared."""

import pytest

from benchmarks.diagnose_ab import summarize


def _run(seconds, selected, drag=0.1):
    return {
        "seconds": seconds,
        "selected": selected,
        "final_check_l1_m": 0.004,
        "improvements": {"drag@1": drag},
    }


def test_speedup_is_base_over_head_and_names_are_compared():
    rows = {
        "light:none:1": {"base": [_run(300, [])], "head": [_run(200, [], drag=0.1000001)]},
        "stiff:internal_damping:0": {
            "base": [_run(400, ["internal_damping"]), _run(420, ["internal_damping"])],
            "head": [_run(250, ["internal_damping"]), _run(270, [])],
        },
    }
    out = summarize(rows)
    light, stiff = out["datasets"]["light:none:1"], out["datasets"]["stiff:internal_damping:0"]
    assert light["speedup"] == pytest.approx(1.5) and light["same_names"]
    assert light["max_improvement_difference"] == pytest.approx(1e-7)
    assert stiff["base_s"] == 410 and stiff["head_s"] == 260 and not stiff["same_names"]
    assert out["speedup"] == pytest.approx((300 + 410) / (200 + 260))
