"""The planted-effect benchmark's versions and budgets: which fits a row was made with (``TOOL_VERSION``),
the decision rule its summary applies (``RULE``), the budget of the tool's runs and the settings that
key a stored row (:func:`run_config`)."""

from __future__ import annotations

import dataclasses

from deform.diagnose.fitting import FitBudget
from deform.diagnose.scoring import MIN_GAIN
from deform.diagnose.selection import DiagnoseBudget


def budget(quick) -> DiagnoseBudget:
    if quick == "smoke":  # pipeline check only (seconds per dataset); numbers meaningless
        return DiagnoseBudget(
            nominal_iterations=3,
            candidate=FitBudget(iterations=2, batch=4, horizon=10),
            max_rounds=2,
            later_round_candidates=2,
            progress=False,
        )
    if quick:
        return DiagnoseBudget.quick(progress=False)
    return DiagnoseBudget(progress=False)


def tool_budget(args) -> DiagnoseBudget:
    """The budget of the tool's runs: ``--quick``, and ``--fits-version N`` for the fits of an
    older tool (6: slow terms on the candidates' fixed windows; 7: rest curvature in the "up"
    convention's roll, not read from each recording; 8: the rope freed at the gripped markers;
    10: every fit at the 10 ms step; 11, a study: slow terms at 5 ms from the 10 ms nominal fit)."""
    version = getattr(args, "fits_version", None) or TOOL_VERSION
    return dataclasses.replace(
        budget(args.quick),
        grow_slow_terms=version >= 7,
        read_roll=version >= 8,
        fit_clamp=version >= 9,
        slow_step_s=SLOW_STEP_S if version >= 11 else None,
        fine_nominal=version >= 12,
    )


# The fits' version; bump when they change: rows of older fits are never reused. v2: transported window
# frames, discretisation-independent internal damping; v3: dissipative candidates started with the nominal
# damping at the material level, contact height grid, equivalence classes, refit noise, ROD.json length
# beyond the markers; v5: a late input also tried with part of the nominal damping removed, and scored at
# the gripped markers on the recorded inputs (its lagging ends had cost it the lag). The decision
# rule is not part of it: every summary re-derives the decisions from the stored candidate scores with
# today's rule (deform.diagnose.scoring.reselect; v4 of the tool changed only the rule). v6: candidates
# scored on the windowed check error (one-second predictions along each check recording), the full
# rollout's improvement kept beside it as "improvement_rollout"; two descents from a new term's grid
# (the better end on held-out fit windows kept); contact friction that never reverses the sliding in
# a step; the contact grid also with the nominal stiffness halved; damping shares 1, 1/2, 1/5. v7: slow
# terms (internal damping) and a reference of their own fitted on windows growing to the one-second
# scoring windows (DiagnoseBudget.grow_slow_terms, on by default); rows of v6 run with
# --grow-slow-terms (config "grow_slow_terms": true) are v7 rows and were relabelled as such. v9: the
# nominal model fits a clamp length past the gripped markers (deform.diagnose.simulator.clamped). v10:
# the wind term is fitted as log strength and azimuth from a grid of directions and strengths
# (terms.ExternalForce); before, its two components started from no wind and reached at most about
# 0.75 m/s^2 per axis; and a clip's mass is fitted as its log from three masses (terms.PointMass):
# before, its fits stopped at about 10.5 g. v11 (a study, `--fits-version 11`, not the tool's default):
# the slow terms (internal damping) and their reference fitted with the model stepped at 5 ms
# (DiagnoseBudget.slow_step_s = SLOW_STEP_S), and every later round once one is selected. v12: as
# v11, but in round 1 the slow terms and their reference start from a nominal model fitted at 5 ms
# of its own (DiagnoseBudget.fine_nominal); its rows are v10 rows with internal_damping refitted
# (FITS_BASE).
TOOL_VERSION = 12
SLOW_STEP_S = 0.005
# the fits version a --refit splices into, where it is not the one before (v11 was a study)
FITS_BASE = {12: 10}
# Rule v7 (after fits v8): a term fitted within a rope's own material level is not named
# (deform.terms.library.INTERNAL_DAMPING_LEVEL). Rule v8: a term fitted beyond its material level
# is also named below the threshold when its interval over check recordings lies above 0
# (deform.diagnose.scoring.nameable). Rule v9: nothing is named in a round where a term fitted within
# its material level does as well as the pick, both less their parameter penalty
# (deform.diagnose.scoring.material_level_suffices). Rule v10: the pick is the nameable candidate with
# the largest improvement less its parameter penalty (deform.diagnose.scoring.choose).
RULE = (
    "v10: the mean windowed improvement above the threshold, or a term beyond its material level "
    "with its 90 % interval above 0; never a term within its material level; the pick the largest "
    "improvement less its parameter penalty, and nothing where a term within its level does as well, "
    "penalised"
)
ROLLOUT_MIN_GAIN = 0.057  # the tool's threshold on the rollout statistic of fits v3-v5 (rule v4)


def tool_min_gain(row: dict) -> float:
    """The tool's threshold for a row: its stored improvements are windowed from fits v6 on."""
    return MIN_GAIN if row["config"].get("tool", 0) >= 6 else ROLLOUT_MIN_GAIN


def run_config(args) -> dict:
    """The settings a stored row depends on: a row is reused only by a run with the same ones."""
    cfg = {
        "quick": args.quick,
        "fit": args.fit,
        "check": args.check,
        "frames": args.frames,
        "tool": getattr(args, "fits_version", None) or TOOL_VERSION,
    }
    if getattr(args, "simulator", "own") != "own":
        cfg["simulator"] = args.simulator
    if getattr(args, "frame_step", 1) != 1:
        cfg["frame_step"] = args.frame_step
    if getattr(args, "noise_mm", None) is not None:
        cfg["noise_mm"] = args.noise_mm
    if getattr(args, "denoise", "auto") != "auto":
        cfg["denoise"] = args.denoise
    return cfg


def refit_budget(args) -> DiagnoseBudget:
    """The tool's budget restricted to the ``--refit`` candidates and one round."""
    return dataclasses.replace(tool_budget(args), candidates=tuple(args.refit), max_rounds=1)


def previous_config(args) -> dict:
    """The configuration of the rows a ``--refit`` splices into: the previous fits version's."""
    version = run_config(args)["tool"]
    return {**run_config(args), "tool": FITS_BASE.get(version, version - 1)}


def stem_of(args) -> str:
    """The name of the result files: ``--stem``, else diagnose[.SIMULATOR]."""
    return args.stem or ("diagnose" if args.simulator == "own" else f"diagnose.{args.simulator}")
