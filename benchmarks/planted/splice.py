"""``--refit``: today's rows made from the previous fits version's, refitting only the round-1
candidates today's fits changed (exact for the first name)."""

from __future__ import annotations

import time

from benchmarks.planted.config import refit_budget, run_config
from deform.diagnose.scoring import MIN_GAIN, PER_PARAM, reselect
from deform.diagnose.selection import diagnose
from deform.diagnose.spec import Inputs


def spliced_row(old: dict, rep: dict, config: dict, seconds: float) -> dict:
    """Today's row made from the previous version's: the round-1 candidates that changed between
    the versions (``rep``, a diagnosis restricted to them, one round) replace theirs; every other
    round-1 candidate is kept. Exact for round 1, hence for the first name: each round-1 candidate
    is fitted on its own from the same nominal fit (``spliced.nominal_check_delta_m`` checks that the
    nominal fit came out the same). Later rounds are those run with the previous fits (the re-derived
    decision ignores them when the first pick changed, see :func:`reselect`)."""
    fresh = {c["name"]: c for c in rep["candidates"] if c["round"] == 1}
    cands = [fresh.pop(c["name"]) if c["round"] == 1 and c["name"] in fresh else c for c in old["candidates"]]
    cands += list(fresh.values())
    tool = reselect(cands, old["nominal_check_l1_m"], MIN_GAIN, PER_PARAM)
    first_same = tool["selected"][:1] == old["selected"][:1]
    row = {
        **old,
        "config": config,
        "selected": tool["selected"],
        "final_check_l1_m": tool["final_check_l1_m"],
        "equivalence_class": old.get("equivalence_class", []) if first_same else tool["selected"][:1],
        "candidates": cands,
        "spliced": {
            "from_tool": old["config"]["tool"],
            "refitted": sorted({c["name"] for c in rep["candidates"]}),
            "nominal_check_delta_m": rep["nominal"]["check_l1_m"] - old["nominal_check_l1_m"],
            "fine_nominal": rep["nominal"].get("fine"),
            "seconds": seconds,
        },
    }
    if "found_round1" in old:  # planted rows (real rods have no effect to find)
        row["found_round1"] = next(
            (c["params"] for c in cands if c["name"] == old["effect"] and c["round"] == 1), {}
        )
    return row


def run_spliced(old: dict, inputs: Inputs, args, t0: float, amend=None) -> dict:
    """Refit the ``--refit`` candidates on ``inputs``, splice them into ``old`` (:func:`spliced_row`),
    let ``amend(row)`` add what only the caller knows (a planted truth's parameter error); -> the row."""
    rep = diagnose(inputs, refit_budget(args)).report
    row = spliced_row(old, rep, run_config(args), time.perf_counter() - t0)
    if amend is not None:
        amend(row)
    return row
