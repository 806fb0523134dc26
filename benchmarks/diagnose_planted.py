"""Benchmark of `deform diagnose` on datasets with one planted effect (and controls), then on the
real recordings DLO1..DLO5 against plain DER.

Planted data: deform.diagnose.planted (finer rod, smaller dt, markers a subset of nodes, 0.3 mm
noise, gripper motions replayed from real DLO2 recordings). The tool is not told the effect.
Writes benchmarks/results/diagnose.{json,md}.

    python benchmarks/diagnose_planted.py [--quick] [--seeds 3] [--control-seeds 5] [--effects a b ...]
        [--real DLO1 ...] [--fit 8 --check 4 --frames 500] [--summary-only]

Every dataset's row is appended to benchmarks/results/diagnose.runs.jsonl as soon as it is done; a
rerun with the same configuration skips the rows already there (resume after an interruption).
The significance rule is reported twice: as the tool ran, and calibrated on the controls
(deform.diagnose.scoring.calibrate_min_gain) and re-applied to the stored candidate scores.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from deform.diagnose.fitting import FitBudget
from deform.diagnose.planted import EFFECTS, generate_planted, oracle_term
from deform.diagnose.scoring import MIN_GAIN, PER_PARAM, calibrate_min_gain, reselect
from deform.diagnose.selection import DiagnoseBudget, diagnose
from deform.diagnose.simulator import CHECK_HORIZON
from deform.diagnose.spec import Inputs, RodSpec
from deform.io.recordings import Recording, find_data_root, load_recordings
from deform.model import gripped_indices
from deform.terms.library import LIBRARY

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results"
RODS = {
    "DLO1": (1.152, 0.0345, 13),
    "DLO2": (0.996, 0.0652, 12),
    "DLO3": (0.998, 0.0968, 12),
    "DLO4": (0.973, 0.022, 12),
    "DLO5": (0.988, 0.0192, 12),
}


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


def param_error(found: dict, truth: dict, edge_m: float) -> dict:
    """Relative error of each planted parameter the term reports. Rest curvature: the tool reports a
    turning per vertex (curvature x marker spacing ``edge_m``) in a material frame whose orientation
    depends on the unobserved twist, so the magnitude |kappa| is compared."""
    if "kappa1_per_vertex" in found:
        k_found = float(np.hypot(found["kappa1_per_vertex"], found["kappa2_per_vertex"])) / edge_m
        k_true = float(np.hypot(truth["kappa1_per_m"], truth["kappa2_per_m"]))
        return {"kappa_per_m": abs(k_found - k_true) / k_true}
    out = {}
    for k, v in truth.items():
        if k in found and v != 0:
            out[k] = abs(found[k] - v) / abs(v)
    return out


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


def _config(args) -> dict:
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


def at_frame_step(spec: RodSpec, recs: list, step: int) -> tuple[RodSpec, list]:
    """Every ``step``-th frame of the simulated recordings, as a camera or motion-capture system at
    ``100 / step`` Hz records them, and ROD.json's frame period to match (the tool resamples them to
    its 100 Hz, ``deform.diagnose.resample``)."""
    if step == 1:
        return spec, recs
    sub = [Recording(name=r.name, positions=r.positions[::step], dt=r.dt * step) for r in recs]
    return spec.model_copy(update={"dt": spec.dt * step}), sub


def load_runs(path: Path, config: dict) -> dict[str, dict]:
    """Rows already computed with the same configuration (the benchmark resumes where it stopped)."""
    done = {}
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                if row.get("config") == config:
                    done[row["key"]] = row
    return done


def finished(key: str, done: dict, runs_path: Path, args) -> bool:
    """Whether the row ``key`` needs no work from this process: computed already (by this process
    or by another one appending to the same runs file), or being computed by another live process
    (:func:`claim`). Parallel runs then share the work instead of repeating it."""
    done.update(load_runs(runs_path, _config(args)))
    return key in done or not claim(key, runs_path)


def _claim_path(key: str, runs_path: Path) -> Path:
    return runs_path.with_name(runs_path.name + ".claims") / hashlib.sha1(key.encode()).hexdigest()


def claim(key: str, runs_path: Path) -> bool:
    """Take the dataset ``key`` of ``runs_path`` for this process: False while another live process
    on this machine holds it. A claim is a file holding its process id, created atomically and
    removed when the row is appended (:func:`append_run`); one left by a process that died is taken
    over. Why: rows are appended only when a dataset is done (minutes), so two processes that
    checked the runs file before either finished used to run the same dataset twice."""
    path = _claim_path(key, runs_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        try:
            holder = int(path.read_text() or 0)
        except (OSError, ValueError):
            holder = 0
        if holder == os.getpid():
            return True
        if holder <= 0:
            return False  # just created, its process id not yet written
        try:
            os.kill(holder, 0)
            return False  # alive: its dataset
        except ProcessLookupError:
            pass
        except PermissionError:
            return False  # alive, another user's
        path.write_text(str(os.getpid()))  # left by a process that died: taken over
        return True
    with os.fdopen(fd, "w") as f:
        f.write(str(os.getpid()))
    return True


def append_run(path: Path, row: dict) -> None:
    """Append ``row`` to the runs file and release its claim (:func:`claim`)."""
    with path.open("a") as f:
        f.write(json.dumps(row) + "\n")
    claim_file = _claim_path(row["key"], path)
    claim_file.unlink(missing_ok=True)
    try:
        claim_file.parent.rmdir()  # the last claim: no empty directory left beside the results
    except OSError:
        pass  # other claims still held


def previous_row(key: str, runs_path: Path, args) -> dict | None:
    """With ``--refit``: the row ``key`` of the previous fits version, which today's refitted
    candidates are spliced into (:func:`spliced_row`), or None (then the dataset is run in full)."""
    if not getattr(args, "refit", None):
        return None
    version = _config(args)["tool"]
    return load_runs(runs_path, {**_config(args), "tool": FITS_BASE.get(version, version - 1)}).get(key)


def refit_budget(args) -> DiagnoseBudget:
    """The tool's budget restricted to the ``--refit`` candidates and one round."""
    return dataclasses.replace(tool_budget(args), candidates=tuple(args.refit), max_rounds=1)


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


def run_spliced(
    old: dict, inputs: Inputs, args, key: str, runs_path: Path, done: dict, t0: float, amend=None
):
    """Refit the ``--refit`` candidates on ``inputs``, splice them into ``old`` (:func:`spliced_row`),
    let ``amend(row)`` add what only the caller knows (a planted truth's parameter error), and store
    the row."""
    rep = diagnose(inputs, refit_budget(args)).report
    row = spliced_row(old, rep, _config(args), time.perf_counter() - t0)
    if amend is not None:
        amend(row)
    append_run(runs_path, row)
    done[key] = row
    print(json.dumps({"key": key, "selected": row["selected"], "spliced": row["spliced"]}), flush=True)


def marker_edge(recs) -> float:
    return float(
        np.median(
            np.concatenate(
                [np.linalg.norm(np.diff(r.positions[::25, 1:-1], axis=1), axis=-1).ravel() for r in recs]
            )
        )
    )


def oracle_check(spec, nominal_params: dict, effect, truth, inputs, quick: bool) -> float | None:
    """Check error of the tool's model class with the right term started at the planted truth
    (nominal refitted with the candidate budget): the 'truth' end of the gap."""
    from deform.diagnose.fitting import fit
    from deform.diagnose.simulator import Nominal, Simulator, arclength_of, per_recording_l1

    s = arclength_of(inputs.fit)
    edge = marker_edge(inputs.fit)
    term = oracle_term(effect, truth, spec.n_vertices, s, edge)
    if term is None:
        return None
    nom = Nominal(
        nominal_params["bend_stiffness_Nm2"],
        nominal_params["twist_stiffness_Nm2"],
        nominal_params["damping_1_per_s"],
        clamp_m=nominal_params.get("clamp_m", 0.0),
    )
    nom.clamp_dm.requires_grad_("clamp_m" in nominal_params)  # fits before v9 freed the rope at the markers
    sim = Simulator(spec, nom, [term])
    fit(sim, inputs.fit, dataclasses.replace(budget(quick).candidate, progress=False), desc="oracle")
    return float(per_recording_l1(sim.predict(inputs.check), inputs.check).mean())


# real gripper motions driving each rod kind; medium is a held-out third rod, run only when asked
# (--rod-kinds medium), so that the stored commands of the light and stiff benchmarks keep their meaning
ELASTICA_SOURCES = {"light": "DLO1", "stiff": "DLO3", "medium": "DLO2"}
DEFAULT_ROD_KINDS = ("light", "stiff")


def as_user_inputs(spec: RodSpec, fit: list, check: list, smooth_noise: bool = True) -> Inputs:
    """The recordings written to files and read back with ROD.json as a user gives them
    (`deform diagnose --rod --fit --check [--denoise off]`): the tool's own input checks and
    conventions apply (a rope longer than its marker span is simulated over the span, with a
    warning; recordings far noisier than the calibrated 0.3 mm are smoothed)."""
    import tempfile

    from deform.diagnose.spec import load_inputs
    from deform.io import save_recording

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, recs in (("fit", fit), ("check", check)):
            (tmp / name).mkdir()
            for i, r in enumerate(recs):
                save_recording(tmp / name / f"{i:02d}.pkl", r.positions)
        (tmp / "rod.json").write_text(json.dumps(spec.model_dump()))
        return load_inputs(tmp / "rod.json", tmp / "fit", tmp / "check", smooth_noise=smooth_noise)


def equivalence_of(rep: dict) -> list[str]:
    """The equivalence class of the first selected term (itself alone when the data tell it apart)."""
    if not rep["selected"]:
        return []
    first = next((c for c in rep["candidates"] if c["name"] == rep["selected"][0] and c["round"] == 1), {})
    return first.get("equivalence_class", rep["selected"][:1])


# the independent simulators: the module that plants the effects and its generator function
INDEPENDENT = {
    "elastica": ("elastica_planted", "generate_elastica"),  # PyElastica, Cosserat rods
    "mujoco": ("mujoco_planted", "generate_mujoco"),  # MuJoCo, a chain of rigid capsules
}


def independent_simulator(simulator: str):
    """-> (EFFECTS, generate, detectability) of an independent simulator's planted-effect module
    (benchmarks/<module>.py; needs ``benchmarks/`` on sys.path)."""
    import importlib

    module, generate = INDEPENDENT[simulator]
    mod = importlib.import_module(module)
    return mod.EFFECTS, getattr(mod, generate), mod.detectability


def independent_rod(kind: str, root: Path | None = None, simulator: str = "elastica") -> tuple[RodSpec, list]:
    """The independent-simulator benchmark's rod of ``kind`` (light, stiff): its spec as a user gives
    it and the recorded train motions of its source rod that drive it."""
    rod = ELASTICA_SOURCES[kind]
    L, M, n = RODS[rod]
    spec = RodSpec(length_m=L, mass_kg=M, n_vertices=n, name=f"{kind}-{simulator}")
    return spec, load_recordings((root or find_data_root()) / rod / "train")


def seeded_sources(sources: list, seed: int, count: int) -> list:
    """``count`` source recordings picked by ``seed`` (with repeats only when there are fewer)."""
    pick = np.random.default_rng(seed).choice(len(sources), count, replace=len(sources) < count)
    return [sources[i] for i in pick]


def run_independent(jobs, args, runs_path: Path, done: dict, simulator: str = "elastica") -> None:
    """Effects planted by a simulator we did not write (``INDEPENDENT``: PyElastica,
    benchmarks/elastica_planted.py, or MuJoCo, benchmarks/mujoco_planted.py) on a light and a stiff
    rod, each driven by real gripper motions; inputs go through the user path."""
    _, generate, detectability = independent_simulator(simulator)

    data = find_data_root()
    controls: dict = {}
    for kind, effect, seed in jobs:
        key = f"{simulator}:{kind}:{effect or 'none'}:{seed}"
        spec, sources = independent_rod(kind, data, simulator)
        src = seeded_sources(sources, seed, args.fit + args.check)
        if finished(key, done, runs_path, args):
            continue
        old = previous_row(key, runs_path, args)
        t0 = time.perf_counter()
        try:
            noise = {"noise_m": args.noise_mm * 1e-3} if args.noise_mm is not None else {}
            recs, truth = generate(effect, src, spec, rod_kind=kind, n_frames=args.frames, seed=seed, **noise)
            t_sim = time.perf_counter() - t0
            if effect is None:
                controls[(kind, seed)] = recs
            pair = controls.get((kind, seed))
            if pair is None and effect is not None and old is None:
                pair, _ = generate(None, src, spec, rod_kind=kind, n_frames=args.frames, seed=seed, **noise)
                controls[(kind, seed)] = pair
        except RuntimeError as exc:  # the simulator's own step diverged: no dataset, stated as such
            if "diverged" not in str(exc):
                raise
            row = {
                "key": key,
                "config": _config(args),
                "kind": "diverged",
                "simulator": simulator,
                "rod_kind": kind,
                "effect": effect or "none",
                "seed": seed,
                "reason": str(exc),
                "seconds": time.perf_counter() - t0,
            }
            append_run(runs_path, row)
            done[key] = row
            print(json.dumps({k: row[k] for k in ("key", "reason")}), flush=True)
            continue
        user_spec, user_recs = at_frame_step(spec, recs, args.frame_step)
        inputs = as_user_inputs(
            user_spec, user_recs[: args.fit], user_recs[args.fit :], smooth_noise=args.denoise != "off"
        )
        if old is not None:
            run_spliced(old, inputs, args, key, runs_path, done, t0)
            continue
        rep = diagnose(inputs, tool_budget(args)).report
        found = next((c["params"] for c in rep["candidates"] if c["name"] == effect and c["round"] == 1), {})
        row = {
            "key": key,
            "config": _config(args),
            "kind": "planted",
            "simulator": simulator,
            "rod_kind": kind,
            "effect": effect or "none",
            "seed": seed,
            "selected": rep["selected"],
            "equivalence_class": equivalence_of(rep),
            "truth": truth,
            "found_round1": found,
            "found_selected": rep["nominal"]["final_params"].get(effect, {}) if effect else {},
            "param_rel_error": {},
            "warnings": rep["nominal"]["warnings"],
            "detectability_l1_m": detectability(recs, pair) if effect is not None else 0.0,
            "nominal_params": rep["nominal"]["params"],
            "clamp_restart": rep["nominal"].get("clamp_restart"),
            "nominal_check_l1_m": rep["nominal"]["check_l1_m"],
            "final_check_l1_m": rep["final_check_l1_m"],
            "candidates": rep["candidates"],
            "findings": rep["localization"]["findings"],
            "seconds_simulate": t_sim,
            "seconds": time.perf_counter() - t0,
            "oracle_check_l1_m": None,
        }
        append_run(runs_path, row)
        done[key] = row
        print(
            json.dumps(
                {
                    k: row[k]
                    for k in (
                        "key",
                        "selected",
                        "equivalence_class",
                        "detectability_l1_m",
                        "nominal_check_l1_m",
                        "final_check_l1_m",
                        "seconds",
                    )
                }
            ),
            flush=True,
        )


def provenance() -> dict:
    """The commit and machine a result comes from (stored with it)."""
    import platform

    from deform.bench import source_commit

    commit = source_commit()
    return {
        "commit": commit,
        "machine": f"{platform.node()}: {os.cpu_count()} CPU cores (shared with other jobs), torch 1 thread",
    }


def calibrate_damping(args) -> dict:
    """The nominal model's material damping level (deform.terms.library.MATERIAL_DAMPING_LEVEL) from
    controls only (no effect planted): the linear damping a free nominal fit gives on
    independent-simulator controls (light and stiff rod, small material damping) and on this
    project's own controls (stored rows); the level = 2x the largest. The factor leaves room for
    ropes damped more than these; drag and contact have measured 5-10x."""
    from elastica_planted import generate_elastica

    from deform.diagnose.fitting import coarse_nominal, fit
    from deform.diagnose.simulator import Nominal, Simulator

    data = find_data_root()
    b = budget(args.quick)
    fitted = []
    for kind in args.rod_kinds:
        spec, sources = independent_rod(kind, data)
        for seed in range(args.control_seeds):
            pick = np.random.default_rng(seed).choice(len(sources), args.fit + args.check, replace=False)
            recs, _ = generate_elastica(
                None, [sources[i] for i in pick], spec, rod_kind=kind, n_frames=args.frames, seed=seed
            )
            inputs = as_user_inputs(spec, recs[: args.fit], recs[args.fit :])
            sim = Simulator(inputs.spec, Nominal(damping_max=20.0))
            coarse_nominal(sim, inputs.fit)
            fit(
                sim,
                inputs.fit,
                dataclasses.replace(b.candidate, iterations=b.nominal_iterations, progress=False),
            )
            fitted.append({"simulator": "elastica", "rod_kind": kind, "seed": seed, **sim.nominal.params()})
            print(json.dumps(fitted[-1]), flush=True)
    own = load_runs(
        RESULTS / "diagnose.runs.jsonl", {"quick": True, "fit": 6, "check": 4, "frames": 300, "tool": 2}
    )
    fitted += [
        {"simulator": "own", "seed": r["seed"], **r["nominal_params"]}
        for r in own.values()
        if r["kind"] == "planted" and r["effect"] == "none"
    ]
    worst = max(f["damping_1_per_s"] for f in fitted)
    out = {
        "command": "python benchmarks/diagnose_planted.py --calibrate-damping " + " ".join(args.rod_kinds),
        **provenance(),
        "controls": fitted,
        "largest_1_per_s": worst,
        "level_1_per_s": round(2 * worst, 2),
    }
    (RESULTS / "diagnose.damping_level.json").write_text(json.dumps(out, indent=2))
    return out


def full_size_timing(args) -> dict:
    """Wall time of `deform diagnose` with the default (full) budget on one independent-simulator case
    of the issue's size (8 + 4 recordings of 500 frames), run as a user runs it: files on disk and
    the command line. -> the row stored in benchmarks/results/diagnose.timing.EFFECT.json."""
    import subprocess
    import tempfile

    from elastica_planted import generate_elastica

    from deform.io import save_recording

    kind, effect = args.rod_kinds[0], (args.effects or ["ground_contact"])[0]
    spec, sources = independent_rod(kind)
    pick = np.random.default_rng(0).choice(len(sources), 12, replace=False)
    recs, _ = generate_elastica(effect, [sources[i] for i in pick], spec, rod_kind=kind, n_frames=500, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, part in (("fit", recs[:8]), ("check", recs[8:])):
            (tmp / name).mkdir()
            for i, r in enumerate(part):
                save_recording(tmp / name / f"{i:02d}.pkl", r.positions)
        (tmp / "rod.json").write_text(
            json.dumps(
                {
                    "length_m": spec.length_m,
                    "mass_kg": spec.mass_kg,
                    "n_vertices": spec.n_vertices,
                    "dt": 0.01,
                }
            )
        )
        cmd = [
            sys.executable,
            "-m",
            "deform.cli",
            "diagnose",
            "--rod",
            str(tmp / "rod.json"),
            "--fit",
            str(tmp / "fit"),
            "--check",
            str(tmp / "check"),
            "--out",
            str(tmp / "out"),
            "--json",
        ]
        t0 = time.perf_counter()
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT.parent)
        seconds = time.perf_counter() - t0
    rep = json.loads(out.stdout) if out.returncode == 0 else {}
    row = {
        "command": "python benchmarks/diagnose_planted.py --full-size-timing --rod-kinds "
        + kind
        + " --effects "
        + effect,
        **provenance(),
        "case": f"elastica {kind} {effect} seed 0, 8 + 4 recordings x 500 frames",
        "budget": "full (default)",
        "seconds_wall": seconds,
        "returncode": out.returncode,
        "selected": rep.get("selected"),
        "stderr_tail": out.stderr[-300:] if out.returncode else "",
    }
    (RESULTS / f"diagnose.timing.{effect}.json").write_text(json.dumps(row, indent=2))
    return row


def run_planted(jobs, args, runs_path: Path, done: dict) -> None:
    data = find_data_root()
    sources = load_recordings(data / "DLO2" / "train")
    L, M, n = RODS["DLO2"]
    spec = RodSpec(length_m=L, mass_kg=M, n_vertices=n, name="DLO2-planted")
    for effect, seed in jobs:
        key = f"{effect or 'none'}:{seed}"
        if finished(key, done, runs_path, args):
            continue
        rng = np.random.default_rng(seed)
        pick = rng.choice(len(sources), args.fit + args.check, replace=False)
        src = [sources[i] for i in pick]
        t0 = time.perf_counter()
        recs, truth = generate_planted(effect, src, spec, n_frames=args.frames, seed=seed)
        inputs = Inputs(spec=spec, fit=recs[: args.fit], check=recs[args.fit :])
        old = previous_row(key, runs_path, args)
        if old is not None:

            def refitted_error(row, effect=effect, truth=truth, inputs=inputs):
                if effect in row["spliced"]["refitted"]:
                    row["param_rel_error"] = param_error(row["found_round1"], truth, marker_edge(inputs.fit))

            run_spliced(old, inputs, args, key, runs_path, done, t0, refitted_error)
            continue
        rep = diagnose(inputs, tool_budget(args)).report
        t_diag = time.perf_counter() - t0
        found = next((c["params"] for c in rep["candidates"] if c["name"] == effect and c["round"] == 1), {})
        fitted = {k: v for k, v in rep["nominal"]["final_params"].items() if k == effect}
        row = {
            "key": key,
            "config": _config(args),
            "kind": "planted",
            "effect": effect or "none",
            "seed": seed,
            "selected": rep["selected"],
            "truth": truth,
            "found_round1": found,
            "found_selected": fitted.get(effect, {}),
            "param_rel_error": param_error(fitted.get(effect) or found, truth, marker_edge(inputs.fit)),
            "nominal_params": rep["nominal"]["params"],
            "clamp_restart": rep["nominal"].get("clamp_restart"),
            "nominal_check_l1_m": rep["nominal"]["check_l1_m"],
            "final_check_l1_m": rep["final_check_l1_m"],
            "candidates": rep["candidates"],
            "findings": rep["localization"]["findings"],
            "seconds_diagnose": t_diag,
        }
        row["oracle_check_l1_m"] = oracle_check(
            spec, rep["nominal"]["params"], effect, truth, inputs, args.quick
        )
        row["seconds"] = time.perf_counter() - t0
        append_run(runs_path, row)
        done[key] = row
        print(
            json.dumps(
                {
                    k: row[k]
                    for k in (
                        "key",
                        "selected",
                        "nominal_check_l1_m",
                        "final_check_l1_m",
                        "oracle_check_l1_m",
                        "seconds",
                    )
                }
            ),
            flush=True,
        )


def run_real(rods, args, runs_path: Path, done: dict) -> None:
    data = find_data_root()
    for rod in rods:
        key = f"real:{rod}"
        if finished(key, done, runs_path, args):
            continue
        L, M, n = RODS[rod]
        recs = load_recordings(data / rod / "train")
        spec = RodSpec(length_m=L, mass_kg=M, n_vertices=n, name=rod)
        # fit on train, check on eval where the rod has eval recordings (DLO1-DLO3), else on later
        # train recordings; through the user path (ROD.json with the rope's real length)
        held = load_recordings(data / rod / "eval")[: args.check] if (data / rod / "eval").is_dir() else []
        inputs = as_user_inputs(spec, recs[: args.fit], held or recs[args.fit : args.fit + args.check])
        t0 = time.perf_counter()
        old = previous_row(key, runs_path, args)
        if old is not None:
            run_spliced(old, inputs, args, key, runs_path, done, t0)
            continue
        rep = diagnose(inputs, tool_budget(args)).report
        row = {
            "key": key,
            "config": _config(args),
            "kind": "real",
            "rod": rod,
            "selected": rep["selected"],
            "check_split": "eval" if held else "train",
            "equivalence_class": equivalence_of(rep),
            "warnings": rep["nominal"]["warnings"],
            "n_frames": [r.n_frames for r in inputs.fit + inputs.check],
            "nominal_check_l1_m": rep["nominal"]["check_l1_m"],
            "final_check_l1_m": rep["final_check_l1_m"],
            "findings": rep["localization"]["findings"],
            "nominal_params": rep["nominal"]["params"],
            "clamp_restart": rep["nominal"].get("clamp_restart"),
            "final_params": rep["nominal"]["final_params"],
            "candidates": rep["candidates"],
            "seconds": time.perf_counter() - t0,
        }
        append_run(runs_path, row)
        done[key] = row
        print(
            json.dumps(
                {k: row[k] for k in ("key", "selected", "nominal_check_l1_m", "final_check_l1_m", "seconds")}
            ),
            flush=True,
        )


def apply_rules(planted: list[dict], real: list[dict], alpha: float) -> dict:
    """Decisions under (a) the rule the tool ran with and (b) the rule calibrated on the controls.
    Controls are judged with a leave-one-control-out calibration (their own scores never set their
    threshold); planted datasets and real rods with the calibration on all controls."""
    controls = [r for r in planted if r["effect"] == "none"]
    n_cand = len(LIBRARY)

    def nulls(rows):
        c = [c for r in rows for c in r["candidates"] if c["round"] == 1]
        return [x["improvement"] for x in c], [x["n_params"] for x in c]

    cal = None
    if len(controls) >= 2:
        imp, k = nulls(controls)
        cal = calibrate_min_gain(imp, n_cand, alpha=alpha, per_param=PER_PARAM, n_params=k)
    for r in planted + real:
        r["as_run"] = {"selected": r["selected"], "final_check_l1_m": r["final_check_l1_m"]}
        tool = reselect(r["candidates"], r["nominal_check_l1_m"], tool_min_gain(r), PER_PARAM)
        same_first = tool["selected"][:1] == r["selected"][:1]
        r["tool"] = {
            "min_gain": tool_min_gain(r),
            **tool,
            "equivalence_class": equivalence_of(r) if same_first else tool["selected"][:1],
        }
        if cal is None:
            continue
        if r.get("effect") == "none":
            others = [c for c in controls if c is not r]
            if len(others) < 2:
                continue
            imp, k = nulls(others)
            mg = calibrate_min_gain(imp, n_cand, alpha=alpha, per_param=PER_PARAM, n_params=k)["min_gain"]
        else:
            mg = cal["min_gain"]
        r["calibrated"] = {
            "min_gain": mg,
            **reselect(r["candidates"], r["nominal_check_l1_m"], mg, PER_PARAM),
        }
    # the rule the rows were run with, read back from the stored thresholds (not today's default)
    ran = sorted(
        {
            round(c["threshold"] - PER_PARAM * c["n_params"], 6)
            for r in planted + real
            for c in r["candidates"]
        }
    )
    return {
        "calibration": cal,
        "tool_rule": {
            "min_gain": ran[0] if len(ran) == 1 else MIN_GAIN,
            "per_param": PER_PARAM,
            "min_gain_values_in_rows": ran,
        },
    }


def _pair(r: dict):
    """The control a dataset is paired with: same seed (same motions), same rod kind."""
    return (r.get("rod_kind"), r["seed"])


def _gaps(r: dict, floor: dict, final: float) -> dict:
    out = {}
    if r["effect"] == "none":
        return out
    o = r.get("oracle_check_l1_m")
    if o is not None:
        gap = r["nominal_check_l1_m"] - o
        out["gap_oracle_m"] = gap
        out["gap_closed_oracle"] = (r["nominal_check_l1_m"] - final) / gap if gap > 1e-5 else None
    if _pair(r) in floor:
        gap = r["nominal_check_l1_m"] - floor[_pair(r)]
        out["gap_control_m"] = gap
        out["gap_closed_control"] = (r["nominal_check_l1_m"] - final) / gap if gap > 1e-5 else None
    return out


def summarise(rows: list[dict], rule: str) -> dict:
    floor = {_pair(r): r["nominal_check_l1_m"] for r in rows if r["effect"] == "none"}
    out = {}
    for eff in sorted({r["effect"] for r in rows}, key=lambda e: (e != "none", e)):
        rs = [r for r in rows if r["effect"] == eff and rule in r]
        if not rs:
            continue
        sel = [r[rule]["selected"] for r in rs]
        right = [(s[:1] == [eff]) if eff != "none" else (s == []) for s in sel]
        finals = [r[rule]["final_check_l1_m"] for r in rs]
        g = [_gaps(r, floor, f) for r, f in zip(rs, finals)]
        go = [x["gap_closed_oracle"] for x in g if x.get("gap_closed_oracle") is not None]
        gc = [x["gap_closed_control"] for x in g if x.get("gap_closed_control") is not None]
        perr = [float(np.mean(list(r["param_rel_error"].values()))) for r in rs if r["param_rel_error"]]
        if eff == "none":
            in_class = right
        elif rule == "tool":
            in_class = [eff in r["tool"]["equivalence_class"] for r in rs]
        else:
            in_class = [eff in r.get("equivalence_class", equivalence_of(r)) for r in rs]
        detect = [r["detectability_l1_m"] for r in rs if r.get("detectability_l1_m") is not None]
        out[eff] = {
            "runs": len(rs),
            "named_correctly": int(sum(right)),
            "rate": float(np.mean(right)),
            "named_in_class": int(sum(in_class)) if rule in ("as_run", "tool") else None,
            "detectability_cm": (float(np.median(detect)) * 100) if detect and eff != "none" else None,
            "selected": [s or ["none"] for s in sel],
            "nominal_check_cm": float(np.mean([r["nominal_check_l1_m"] for r in rs]) * 100),
            "final_check_cm": float(np.mean(finals) * 100),
            "oracle_check_cm": (
                float(np.mean([r["oracle_check_l1_m"] for r in rs]) * 100)
                if all(r.get("oracle_check_l1_m") is not None for r in rs)
                else None
            ),
            "gap_closed_oracle_median": float(np.median(go)) if go else None,
            "gap_closed_control_median": float(np.median(gc)) if gc else None,
            "gap_closed_oracle_values": go,
            "gap_closed_control_values": gc,
            "param_rel_error_median": float(np.median(perr)) if perr else None,
        }
    return out


def _fmt(x, pct=True):
    return "-" if x is None else (f"{x * 100:.0f} %" if pct else f"{x:.3f}")


def _pooled_gap(summ: dict) -> str:
    """The median gap closed over every planted dataset that has one (all effects pooled)."""
    out = ""
    for key, label in (("oracle", "the truth-started oracle"), ("control", "the paired control")):
        vals = [v for k, s in summ.items() if k != "none" for v in s.get(f"gap_closed_{key}_values") or []]
        if vals:
            out += (
                f" Median gap closed between the nominal model and {label}, all planted datasets with a"
                f" gap: {np.median(vals) * 100:.0f} % ({len(vals)} datasets)."
            )
    return out


def write(result: dict, stem: str = "diagnose") -> None:
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=2))
    title = {
        "elastica": "planted-effect benchmark, recordings from PyElastica (an independent simulator)",
        "mujoco": "planted-effect benchmark, recordings from MuJoCo (an independent simulator)",
    }.get(result.get("simulator"), "planted-effect benchmark")
    lines = [
        f"# deform diagnose: {title}",
        "",
        f"Run: `{result['command']}` on {result['machine']}; {result['seconds_total_runs']:.0f} s of "
        f"dataset runs (sum over the rows in `{result.get('runs_file', stem + '.runs.jsonl')}`).",
        "",
        f"Budget: {result['budget']}",
        "",
    ]
    for r in result.get("diverged", []):
        lines += [f"No dataset for `{r['key']}`: {r['reason']} (the simulator's own step).", ""]
    cal = result["rules"]["calibration"]
    if cal:
        lines += [
            f"Calibrated rule (from {cal['n_null']} round-1 control improvements, parameter penalty "
            f"{cal['per_param'] * 100:.0f} %/param removed): mean {cal['mu'] * 100:.2f} %, sd {cal['sd'] * 100:.2f} %, "
            f"z = {cal['z']:.2f} (alpha {cal['alpha']} over {len(LIBRARY)} candidates) -> "
            f"min gain {cal['min_gain'] * 100:.2f} % + {cal['per_param'] * 100:.0f} %/param. Controls are "
            f"judged leave-one-control-out.",
            "",
        ]
    lines += [
        f"Decisions are re-derived from the stored candidate scores (exact: the fits are those of tool "
        f"v{result['fits_of_tool_version']}; after a first pick the rows were run with no longer matters for the first name). "
        f"Tool rule {RULE}: {MIN_GAIN * 100:.1f} % + {PER_PARAM * 100:.0f} %/param.",
        "",
    ]
    for rule, title in (
        ("tool", f"Rule of the tool ({RULE})"),
        ("calibrated", "Calibrated rule (same form, threshold from this benchmark's controls)"),
        (
            "as_run",
            "Decisions as the rows were run "
            f"({result['rules']['tool_rule']['min_gain'] * 100:.1f} % + "
            f"{result['rules']['tool_rule']['per_param'] * 100:.0f} %/param, with the rest of the rule "
            "of their day)",
        ),
    ):
        summ = result["summary"].get(rule)
        if not summ:
            continue
        tot = sum(s["runs"] for k, s in summ.items() if k != "none")
        ok = sum(s["named_correctly"] for k, s in summ.items() if k != "none")
        in_class = sum(s["named_in_class"] or 0 for k, s in summ.items() if k != "none")
        lines += [
            f"## {title}",
            "",
            f"Planted effects named first: {ok}/{tot}"
            + (
                f" (the truth in the named equivalence class: {in_class}/{tot})"
                if rule in ("as_run", "tool")
                else ""
            )
            + f"; controls `none`: {summ.get('none', {}).get('named_correctly', 0)}/{summ.get('none', {}).get('runs', 0)}."
            + _pooled_gap(summ),
            "",
            "| planted effect | runs | named correctly | in class | marker L1 vs control [cm] | check nominal [cm] | after [cm] | oracle [cm] | gap closed vs oracle (median) | vs control (median) | param rel. error (median) |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for eff, s in summ.items():
            lines.append(
                f"| {eff} | {s['runs']} | {s['named_correctly']}/{s['runs']} | "
                f"{'-' if s.get('named_in_class') is None else str(s['named_in_class']) + '/' + str(s['runs'])} | "
                f"{'-' if s.get('detectability_cm') is None else format(s['detectability_cm'], '.2f')} | {s['nominal_check_cm']:.3f} | "
                f"{s['final_check_cm']:.3f} | {_fmt(s['oracle_check_cm'] and s['oracle_check_cm'] / 100 * 100, False) if s['oracle_check_cm'] is not None else '-'} | "
                f"{_fmt(s['gap_closed_oracle_median'])} | {_fmt(s['gap_closed_control_median'])} | "
                f"{_fmt(s['param_rel_error_median'])} |"
            )
        lines.append("")
    lines += ["## Per run", ""]
    for r in result["planted"]:
        cal_sel = r.get("calibrated", {}).get("selected")
        lines.append(
            f"- {r.get('rod_kind', '') + ' ' if r.get('rod_kind') else ''}{r['effect']} seed {r['seed']}: "
            f"tool {r['tool']['selected'] or ['none']}, as run {r['selected'] or ['none']}"
            + (f" (class {r['equivalence_class']})" if len(r.get("equivalence_class", [])) > 1 else "")
            + (
                f", marker L1 vs control {r['detectability_l1_m'] * 100:.2f} cm"
                if r.get("detectability_l1_m")
                else ""
            )
            + ", calibrated "
            f"{(cal_sel or ['none']) if cal_sel is not None else '-'}; {r['nominal_check_l1_m'] * 100:.3f} -> "
            f"{r['final_check_l1_m'] * 100:.3f} cm (oracle {_fmt(r.get('oracle_check_l1_m') and r['oracle_check_l1_m'] * 100, False)}); "
            f"params {json.dumps({k: round(v, 4) for k, v in (r['found_selected'] or r['found_round1']).items()})} "
            f"truth {json.dumps(r['truth'])}; {r['seconds']:.0f} s"
        )
    if result["real"]:
        lines += [
            "",
            "## Real recordings against plain DER",
            "",
            "| rod | selected (tool) | selected (as run) | selected (calibrated) | check before [cm] | after (tool) [cm] | best round-1 candidates (improvement) | s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in result["real"]:
            top = sorted((c for c in r["candidates"] if c["round"] == 1), key=lambda c: -c["improvement"])[:3]
            cs = r.get("calibrated", {}).get("selected")
            lines.append(
                f"| {r['rod']} | {', '.join(r['tool']['selected']) or 'none'} | {', '.join(r['selected']) or 'none'} | "
                f"{(', '.join(cs) or 'none') if cs is not None else '-'} | {r['nominal_check_l1_m'] * 100:.3f} | "
                f"{r['tool']['final_check_l1_m'] * 100:.3f} | "
                + ", ".join(f"{c['name']} {c['improvement'] * 100:+.1f} %" for c in top)
                + f" | {r['seconds']:.0f} |"
            )
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")


def _sources(seed: int, count: int):
    sources = load_recordings(find_data_root() / "DLO2" / "train")
    pick = np.random.default_rng(seed).choice(len(sources), count, replace=False)
    L, M, n = RODS["DLO2"]
    return [sources[i] for i in pick], RodSpec(length_m=L, mass_kg=M, n_vertices=n, name="DLO2-planted")


def mass_equivalence(seed: int, args) -> dict:
    """How much of the planted marker mass is a uniform mass factor (= stiffness / s, unobservable when
    stiffness is fitted): the planted data against (a) the control and (b) the control with EI and GJ
    divided by s, s = (free rod mass + marker masses) / free rod mass; same motions, same noise."""
    from deform.diagnose.planted import _layout

    src, spec = _sources(seed, args.fit + args.check)
    recs, truth = generate_planted("mass_scale", src, spec, n_frames=args.frames, seed=seed)
    ctrl, _ = generate_planted(None, src, spec, n_frames=args.frames, seed=seed)
    X0, ids = _layout(src[0].positions[0], 3)
    e = np.linalg.norm(np.diff(X0, axis=0), axis=-1)
    m = spec.mass_kg * np.concatenate([[e[0] / 2], (e[:-1] + e[1:]) / 2, [e[-1] / 2]]) / e.sum()
    free = np.ones(len(X0), bool)
    free[gripped_indices(len(X0))] = False
    s = (m[free].sum() + truth["marker_mass_kg"] * np.isin(np.arange(len(X0)), ids)[free].sum()) / m[
        free
    ].sum()
    eq, _ = generate_planted(None, src, spec, n_frames=args.frames, seed=seed, ei=3e-3 / s, gj=2e-3 / s)

    def diff(a, b):
        return float(
            np.mean([np.abs(x.positions[:, 2:-2] - y.positions[:, 2:-2]).mean() for x, y in zip(a, b)])
        )

    return {
        "seed": seed,
        "scale": float(s),
        "vs_control_mm": diff(recs, ctrl) * 1e3,
        "vs_uniform_scale_mm": diff(recs, eq) * 1e3,
    }


def damping_scan(seed: int, args) -> list[dict]:
    """Check error of the tool's model on planted internal-damping data with the nominal parameters
    fixed and the term's nu swept (the truth is 5e-5 m^4/s): how much the term can explain at all."""
    import math

    from deform.diagnose.simulator import Nominal, Simulator, arclength_of, per_recording_l1
    from deform.terms.library import make_term

    src, spec = _sources(seed, args.fit + args.check)
    recs, _ = generate_planted("internal_damping", src, spec, n_frames=args.frames, seed=seed)
    fit_recs, chk = recs[: args.fit], recs[args.fit :]
    out = []
    for c in (0.4, 0.7):
        for nu in (0.0, 1e-5, 5e-5, 2e-4, 1e-3):
            terms = []
            if nu:
                t = make_term("internal_damping", spec.n_vertices, arclength_of(fit_recs))
                with torch.no_grad():
                    t.log_nu.fill_(math.log(nu / t.scale))
                terms = [t]
            sim = Simulator(spec, Nominal(3.1e-3, 2.0e-3, c), terms)
            out.append(
                {
                    "damping_1_per_s": c,
                    "nu_m4_per_s": nu,
                    "check_l1_cm": float(per_recording_l1(sim.predict(chk), chk).mean() * 100),
                }
            )
            print(json.dumps(out[-1]), flush=True)
    return out


def hidden_nodes_study(seed: int, args) -> list[dict]:
    """Can a finer tool model tell a marker mass from a uniform one? On the control and on planted
    marker masses of 4 g (the benchmark's) and 10 g, the nominal fit, then at 0 and 1 hidden node per
    marker interval a reference refit and the mass_scale candidate (same budget, scored as the tool
    scores candidates)."""
    from deform.diagnose.fitting import coarse_nominal, fit
    from deform.diagnose.scoring import score
    from deform.diagnose.selection import fit_and_check
    from deform.diagnose.simulator import Nominal, Simulator, arclength_of, per_recording_l1
    from deform.terms.library import make_term

    src, spec = _sources(seed, args.fit + args.check)
    quick = budget(True)
    cb = dataclasses.replace(quick.candidate, progress=False)
    out = []
    for effect, kg in ((None, 0.0), ("mass_scale", 0.004), ("mass_scale", 0.010)):
        recs, _ = generate_planted(
            effect,
            src,
            spec,
            n_frames=args.frames,
            seed=seed,
            truth_override={"marker_mass_kg": kg} if effect else None,
        )
        inputs = Inputs(spec=spec, fit=recs[: args.fit], check=recs[args.fit :])
        sim = Simulator(spec, Nominal())
        coarse_nominal(sim, inputs.fit)
        fit(sim, inputs.fit, dataclasses.replace(cb, iterations=quick.nominal_iterations))
        e_nom = per_recording_l1(sim.predict(inputs.check), inputs.check)
        for hidden in (0, 1):
            t0 = time.perf_counter()
            ref, c_ref = fit_and_check(spec, sim.nominal, [], inputs, cb, "reference", hidden=hidden)
            e_ref = c_ref.rollout  # this study predates the windowed statistic: kept on the rollout
            term = make_term(
                "mass_scale",
                ref.n,
                ref.node_arclength(arclength_of(inputs.fit)),
                {"rod_mass_kg": spec.mass_kg},
            )
            _, c = fit_and_check(
                spec, sim.nominal, [term], inputs, cb, "mass_scale", new_term=term, hidden=hidden
            )
            e = c.rollout
            sc = score(e_ref, e, term.n_params)
            out.append(
                {
                    "seed": seed,
                    "marker_mass_kg": kg,
                    "hidden_nodes": hidden,
                    "nominal_check_cm": float(e_nom.mean() * 100),
                    "reference_check_cm": float(e_ref.mean() * 100),
                    "mass_scale_check_cm": float(e.mean() * 100),
                    "improvement": sc.improvement,
                    "ci90": [sc.ci_low, sc.ci_high],
                    "significant": sc.significant,
                    "fitted_marker_mass_kg": term.params()["marker_mass_kg"],
                    "seconds": time.perf_counter() - t0,
                }
            )
            print(json.dumps(out[-1]), flush=True)
    return out


def damping_study(kind: str, seed: int, args, variants=((0, None), (1, None))) -> list[dict]:
    """Would another fit see PyElastica's internal damping? On the planted dataset and its paired
    control (same motions and noise), the nominal fit at marker resolution, then per variant
    ``(hidden, final_horizon)`` a reference refit and the internal_damping candidate (same budget,
    scored on the windowed check error as the tool scores candidates): ``hidden`` nodes per marker
    interval (--hidden-damping), fit windows growing to ``final_horizon`` steps (--growing-windows)."""
    from elastica_planted import generate_elastica

    from deform.diagnose.fitting import coarse_nominal, fit
    from deform.diagnose.scoring import score
    from deform.diagnose.selection import fit_and_check
    from deform.diagnose.simulator import Nominal, Simulator, arclength_of
    from deform.terms.library import make_term

    spec, sources = independent_rod(kind)
    src = seeded_sources(sources, seed, args.fit + args.check)
    quick = budget(True)
    cb = dataclasses.replace(quick.candidate, progress=False)
    out = []
    for effect in ("internal_damping", None):
        recs, _ = generate_elastica(effect, src, spec, rod_kind=kind, n_frames=args.frames, seed=seed)
        inputs = as_user_inputs(spec, recs[: args.fit], recs[args.fit :])
        sim = Simulator(inputs.spec, Nominal())
        coarse_nominal(sim, inputs.fit)
        fit(sim, inputs.fit, dataclasses.replace(cb, iterations=quick.nominal_iterations))
        for hidden, final_horizon in variants:
            t0 = time.perf_counter()
            vb = dataclasses.replace(cb, final_horizon=final_horizon)
            ref, c_ref = fit_and_check(inputs.spec, sim.nominal, [], inputs, vb, "reference", hidden=hidden)
            term = make_term("internal_damping", ref.n, ref.node_arclength(arclength_of(inputs.fit)), {})
            _, c = fit_and_check(
                inputs.spec, sim.nominal, [term], inputs, vb, "internal_damping", new_term=term, hidden=hidden
            )
            sc = score(c_ref.window, c.window, term.n_params)
            out.append(
                {
                    "rod_kind": kind,
                    "effect": effect or "none",
                    "seed": seed,
                    "hidden_nodes": hidden,
                    "final_horizon": final_horizon,
                    "reference_window_cm": float(c_ref.window.mean() * 100),
                    "internal_damping_window_cm": float(c.window.mean() * 100),
                    "improvement": sc.improvement,
                    "significant": sc.significant,
                    "improvement_rollout": score(c_ref.rollout, c.rollout, term.n_params).improvement,
                    "fitted_nu_m4_per_s": term.params()["bending_rate_damping_m4_per_s"],
                    "nominal": sim.nominal.params(),
                    "seconds": time.perf_counter() - t0,
                    **provenance(),
                }
            )
            print(json.dumps(out[-1]), flush=True)
    return out


def own_start_study(
    seed: int, src: list, spec: RodSpec, args, start: int = 50, frames: int = 100
) -> list[dict]:
    """The truth's own model (its 3x finer rod, steps and planted damping) started at frame ``start``
    from the truth's exact nodes, or from the markers alone with the nodes between them
    interpolated (:func:`refine_markers`, as any tool must start), with and without the damping:
    the marker L1 over the next ``frames`` frames against the noise-free planted recordings. Why:
    started from the markers the truth's physics predicted the check recordings worse than the same
    rod without the damping; this tells the model's resolution from the state the markers hide."""
    import math

    from deform.diagnose.simulator import Nominal, Simulator, arclength_of, refine_markers

    nodes: list = []
    recs, truth = generate_planted(
        "internal_damping", src, spec, n_frames=args.frames, seed=seed, noise_m=0.0, nodes_out=nodes
    )
    X, ids = torch.from_numpy(nodes[0]), nodes[1]
    grips = torch.from_numpy(np.stack([r.positions for r in recs]))[:, :, gripped_indices(spec.n_vertices)]
    s = arclength_of(recs)
    out = []
    for origin in ("exact", "markers"):
        for damped in (False, True):
            probe = Simulator(spec, Nominal(), hidden=2)
            terms = []
            if damped:
                terms = [
                    oracle_term(
                        "internal_damping", truth, probe.n, probe.node_arclength(s), marker_edge(recs)
                    )
                ]
            nom = Nominal(3e-3, 2e-3, 1.0, damping_max=10.0)
            nom.set_clamp(0.0, fitted=False)
            sim = Simulator(spec, nom, terms, hidden=2, substeps=5)  # the generator's rod and step
            sim.sync()
            x0, x1 = X[:, start], X[:, start + 1]
            if origin == "markers":
                x0, x1 = refine_markers(x0[:, ids], 2), refine_markers(x1[:, ids], 2)
            state = sim.model.initial_state(x0, x1, dt=spec.dt)
            errors = []
            with torch.no_grad():
                for k in range(start + 2, start + 2 + frames):
                    for j in range(1, sim.substeps + 1):
                        f = k - 1 + j / sim.substeps
                        i = min(math.floor(f), grips.shape[1] - 2)
                        state = sim.model.step(state, (1 - (f - i)) * grips[:, i] + (f - i) * grips[:, i + 1])
                    errors.append(float((state.x[:, ids] - X[:, k][:, ids]).abs().mean()))
            out.append(
                {
                    "study": "start_state",
                    "effect": "internal_damping",
                    "seed": seed,
                    "start_from": origin,
                    "model_with_planted_damping": damped,
                    "start_frame": start,
                    "frames": frames,
                    "marker_l1_cm": float(np.mean(errors) * 100),
                    "marker_l1_after_1_10_100_cm": [errors[i] * 100 for i in (0, 9, frames - 1)],
                    **provenance(),
                }
            )
            print(json.dumps(out[-1]), flush=True)
    return out


def own_resolution_study(seed: int, args) -> list[dict]:
    """Would a model finer than the markers name the own simulator's internal damping, which a
    stiffness variation takes at marker resolution? On the planted dataset and its paired control
    (same motions and noise), per resolution (0, 1 hidden node per marker interval): the nominal fit
    at that resolution, then a reference and the internal_damping and stiffness_variation
    candidates (the tool's quick budget, scored as the tool scores candidates). Also the check error
    of the truth's own parameters (no fit) at 0, 1 and 2 hidden nodes, with and without the damping:
    how much of the check error the damping is at all."""
    from deform.diagnose.fitting import fit_nominal
    from deform.diagnose.scoring import score
    from deform.diagnose.selection import CheckErrors, fit_and_check
    from deform.diagnose.simulator import Nominal, Simulator, arclength_of, clamp_bound
    from deform.terms.library import make_term

    src, spec = _sources(seed, args.fit + args.check)
    quick = budget(True)
    cb = dataclasses.replace(quick.candidate, progress=False)
    nb = dataclasses.replace(cb, iterations=quick.nominal_iterations)
    out = own_start_study(seed, src, spec, args)
    for effect in ("internal_damping", None):
        recs, truth = generate_planted(effect, src, spec, n_frames=args.frames, seed=seed)
        inputs = Inputs(spec=spec, fit=recs[: args.fit], check=recs[args.fit :])
        s = arclength_of(inputs.fit)
        # the truth's parameters, no fit; the truth is a 3x finer rod (2 hidden nodes) at 5 steps a frame
        for hidden, substeps in ((0, None), (1, None), (2, None), (2, 5)):
            for damped in (False, True) if effect else (False,):
                probe = Simulator(spec, Nominal(), hidden=hidden)
                terms = []
                if damped:
                    terms = [
                        oracle_term(effect, truth, probe.n, probe.node_arclength(s), marker_edge(inputs.fit))
                    ]
                nom = Nominal(3e-3, 2e-3, 1.0, damping_max=10.0)
                nom.set_clamp(0.0, fitted=False)
                sim = Simulator(spec, nom, terms, hidden=hidden, substeps=substeps)
                c = CheckErrors.of(sim, inputs.check)
                out.append(
                    {
                        "study": "truth_parameters",
                        "effect": effect or "none",
                        "seed": seed,
                        "hidden_nodes": hidden,
                        "steps_per_frame": sim.substeps,
                        "with_planted_damping": damped,
                        "check_cm": float(c.rollout.mean() * 100),
                        "check_window_cm": float(c.window.mean() * 100),
                        **provenance(),
                    }
                )
                print(json.dumps(out[-1]), flush=True)
        for hidden in (0, 1):
            t0 = time.perf_counter()
            nominal = Nominal()
            nominal.set_clamp(0.0, fitted=True)
            sim = Simulator(spec, nominal, hidden=hidden)
            fit_nominal(sim, inputs.fit, nb, 0.5 * clamp_bound(spec))
            c_nom = CheckErrors.of(sim, inputs.check)
            refs: dict = {}
            for name in ("internal_damping", "stiffness_variation"):
                term = make_term(name, sim.n, sim.node_arclength(s), {})
                tb = dataclasses.replace(cb, final_horizon=CHECK_HORIZON if term.slow else None)
                if tb.final_horizon not in refs:  # as the tool: a refit that came out worse is not used
                    _, c_ref = fit_and_check(spec, sim.nominal, [], inputs, tb, "reference", hidden=hidden)
                    refs[tb.final_horizon] = c_nom if c_ref.window.mean() > c_nom.window.mean() else c_ref
                c_ref = refs[tb.final_horizon]
                _, c = fit_and_check(
                    spec, sim.nominal, [term], inputs, tb, name, new_term=term, hidden=hidden
                )
                sc = score(c_ref.window, c.window, term.n_params)
                out.append(
                    {
                        "study": "fitted",
                        "effect": effect or "none",
                        "seed": seed,
                        "hidden_nodes": hidden,
                        "candidate": name,
                        "nominal": sim.nominal.params(),
                        "nominal_check_cm": float(c_nom.rollout.mean() * 100),
                        "reference_window_cm": float(c_ref.window.mean() * 100),
                        "candidate_window_cm": float(c.window.mean() * 100),
                        "improvement": sc.improvement,
                        "improvement_ci90": [sc.ci_low, sc.ci_high],
                        "threshold": sc.threshold,
                        "params": term.params(),
                        "seconds_so_far": time.perf_counter() - t0,
                        **provenance(),
                    }
                )
                print(json.dumps(out[-1]), flush=True)
    return out


def step_scan(kind: str, seed: int, args, simulator: str = "elastica") -> list[dict]:
    """Does the model's own step hide a light rope's internal damping? On an independent simulator's
    planted internal damping and its paired control: the tool's nominal fit (10 ms steps), then the
    check errors (no further fit) with the nominal parameters held and the internal_damping term at
    fixed sizes, the model stepped at 10, 5 and 2.5 ms (rows also with the nominal damping cut to a
    fifth). Where the check error is lowest at nu 0 with 10 ms steps, the step's own dissipation
    stands in for the rope's (DiagnoseBudget.slow_step_s)."""
    import math

    from deform.diagnose.fitting import fit_nominal
    from deform.diagnose.selection import CheckErrors
    from deform.diagnose.simulator import Nominal, Simulator, arclength_of, clamp_bound
    from deform.terms.library import make_term

    _, generate, _ = independent_simulator(simulator)
    spec, sources = independent_rod(kind, simulator=simulator)
    src = seeded_sources(sources, seed, args.fit + args.check)
    quick = budget(True)
    nb = dataclasses.replace(quick.candidate, progress=False, iterations=quick.nominal_iterations)
    out = []
    for effect in ("internal_damping", None):
        recs, truth = generate(effect, src, spec, rod_kind=kind, n_frames=args.frames, seed=seed)
        inputs = as_user_inputs(spec, recs[: args.fit], recs[args.fit :])
        sim = Simulator(inputs.spec, Nominal())
        fit_nominal(sim, inputs.fit, nb, 0.5 * clamp_bound(inputs.spec))
        s = arclength_of(inputs.fit)
        nominal = sim.nominal.params()
        for step in (0.01, 0.005, 0.0025):
            for damping_share in (1.0, 0.2):
                for nu in (0.0, 3e-5, 1e-4, 2e-4, 4e-4):
                    nom = copy.deepcopy(sim.nominal)
                    with torch.no_grad():
                        nom.log_damping.fill_(math.log(nominal["damping_1_per_s"] * damping_share))
                    terms = []
                    if nu > 0:
                        term = make_term("internal_damping", spec.n_vertices, s, {})
                        with torch.no_grad():
                            term.log_nu.fill_(math.log(nu / term.scale))
                        terms = [term]
                    c = CheckErrors.of(Simulator(inputs.spec, nom, terms, max_step_s=step), inputs.check)
                    out.append(
                        {
                            "simulator": simulator,
                            "rod_kind": kind,
                            "effect": effect or "none",
                            "seed": seed,
                            "planted": {k: v for k, v in truth.items() if k not in ("rod", "numerics")},
                            "nominal": nominal,
                            "model_step_s": step,
                            "nominal_damping_share": damping_share,
                            "nu_m4_per_s": nu,
                            "check_window_cm": float(c.window.mean() * 100),
                            "check_rollout_cm": float(c.rollout.mean() * 100),
                            **provenance(),
                        }
                    )
                    print(json.dumps(out[-1]), flush=True)
    return out


def fine_nominal_study(job: str, args) -> dict:
    """The lead the slow-step study left: is the internal damping at 5 ms still named on a control
    when the nominal model is fitted at 5 ms from scratch first? ``job`` is SIMULATOR:KIND:EFFECT:SEED
    (``own:-:none:1``, ``elastica:light:internal_damping:0``). The internal_damping candidate at 5 ms
    (growing windows, the quick budget) against a reference refitted at 5 ms, started from the
    10 ms nominal fit (fits v11) and from a 5 ms nominal fit of its own, each reference falling back
    to the better nominal model's check errors as the tool's does."""
    from deform.diagnose.fitting import fit_nominal
    from deform.diagnose.scoring import nameable, score
    from deform.diagnose.selection import CheckErrors, fit_and_check, refit_reference
    from deform.diagnose.simulator import Nominal, Simulator, arclength_of, clamp_bound
    from deform.terms.library import make_term

    sim_name, kind, effect, seed = job.split(":")
    seed, effect = int(seed), (None if effect == "none" else effect)
    t0 = time.perf_counter()
    if sim_name == "own":
        src, spec = _sources(seed, 10)
        recs, _ = generate_planted(effect, src, spec, n_frames=300, seed=seed)
        inputs = Inputs(spec=spec, fit=recs[:6], check=recs[6:])
    else:
        _, generate, _ = independent_simulator(sim_name)
        rod, sources = independent_rod(kind, simulator=sim_name)
        recs, _ = generate(
            effect, seeded_sources(sources, seed, 12), rod, rod_kind=kind, n_frames=300, seed=seed
        )
        inputs = as_user_inputs(rod, recs[:8], recs[8:])
    spec, quick = inputs.spec, budget(True)
    cb = dataclasses.replace(quick.candidate, progress=False)
    nb = dataclasses.replace(cb, iterations=quick.nominal_iterations)
    coarse = Simulator(spec, Nominal())
    fit_nominal(coarse, inputs.fit, nb, 0.5 * clamp_bound(spec))
    fine = Simulator(spec, Nominal(), max_step_s=SLOW_STEP_S)
    fit_nominal(fine, inputs.fit, nb, 0.5 * clamp_bound(spec))
    c_coarse, c_fine = CheckErrors.of(coarse, inputs.check), CheckErrors.of(fine, inputs.check)
    best = c_fine if c_fine.window.mean() < c_coarse.window.mean() else c_coarse
    tb = dataclasses.replace(cb, final_horizon=CHECK_HORIZON, max_step_s=SLOW_STEP_S)
    row = {
        "job": job,
        "nominal_10ms": coarse.nominal.params(),
        "nominal_5ms": fine.nominal.params(),
        "check_window_cm_10ms": float(c_coarse.window.mean() * 100),
        "check_window_cm_5ms": float(c_fine.window.mean() * 100),
    }
    for label, nominal, current in (
        ("from_10ms", coarse.nominal, c_coarse),
        ("from_5ms", fine.nominal, best),
    ):
        c_ref = refit_reference(spec, nominal, [], inputs, tb, current, "reference")
        term = make_term("internal_damping", spec.n_vertices, arclength_of(inputs.fit), {})
        _, c = fit_and_check(spec, nominal, [term], inputs, tb, "internal_damping", new_term=term)
        sc = score(c_ref.window, c.window, term.n_params)
        row[label] = {
            "reference_window_cm": float(c_ref.window.mean() * 100),
            "candidate_window_cm": float(c.window.mean() * 100),
            "improvement": sc.improvement,
            "improvement_ci90": [sc.ci_low, sc.ci_high],
            "params": term.params(),
            "nameable": bool(nameable(term.name, term.params(), sc.improvement, sc.ci_low, sc.threshold)),
        }
    row["seconds"] = time.perf_counter() - t0
    row.update(provenance())
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    import sys

    p = argparse.ArgumentParser()
    p.add_argument("--quick", action="store_true")
    p.add_argument(
        "--smoke", action="store_true", help="tiny budget: checks the pipeline, numbers meaningless"
    )
    p.add_argument("--seeds", type=int, default=3, help="seeds per planted effect")
    p.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="independent simulators: start at this seed (held-out seeds beside a stored benchmark)",
    )
    p.add_argument("--control-seeds", type=int, default=5, help="control datasets (no effect)")
    p.add_argument("--effects", nargs="*", default=None)
    p.add_argument("--real", nargs="*", default=list(RODS))
    p.add_argument("--fit", type=int, default=8)
    p.add_argument("--check", type=int, default=4)
    p.add_argument("--frames", type=int, default=500)
    p.add_argument(
        "--noise-mm",
        type=float,
        default=None,
        help="independent simulators: marker noise (sd per coordinate) [mm] instead of the generator's 0.3",
    )
    p.add_argument(
        "--denoise",
        choices=("auto", "off"),
        default="auto",
        help="independent simulators: the tool's --denoise (off: recordings are never smoothed)",
    )
    p.add_argument(
        "--frame-step",
        type=int,
        default=1,
        help="independent simulators: give the tool every K-th frame (recordings at 100/K Hz; "
        "marker L1 and the rows' frames stay at 100 Hz)",
    )
    p.add_argument(
        "--alpha", type=float, default=0.05, help="family-wise false-positive rate of the calibrated rule"
    )
    p.add_argument(
        "--simulator",
        choices=("own", *INDEPENDENT),
        default="own",
        help="who plants the effects: this project's simulator, PyElastica or MuJoCo (pip install '.[bench]')",
    )
    p.add_argument(
        "--rod-kinds",
        nargs="*",
        default=list(DEFAULT_ROD_KINDS),
        choices=list(ELASTICA_SOURCES),
        help="elastica, mujoco: light (DLO1 motions), stiff (DLO3); medium (DLO2) only when asked",
    )
    p.add_argument(
        "--runs",
        default=None,
        help="incremental results (resumed); default benchmarks/results/<stem>.runs.jsonl",
    )
    p.add_argument(
        "--summary-only", action="store_true", help="only rebuild diagnose.{json,md} from the runs file"
    )
    p.add_argument(
        "--mass-equivalence",
        type=int,
        nargs="*",
        default=None,
        metavar="SEED",
        help="only measure how much of the planted marker mass is a uniform factor (prints JSON)",
    )
    p.add_argument(
        "--damping-scan",
        type=int,
        default=None,
        metavar="SEED",
        help="only sweep the internal-damping term on planted data with fixed nominal parameters",
    )
    p.add_argument(
        "--hidden-nodes",
        type=int,
        nargs="*",
        default=None,
        metavar="SEED",
        help="only compare the mass_scale candidate at 0 and 1 hidden node per marker interval (JSON rows)",
    )
    p.add_argument(
        "--hidden-damping",
        nargs="*",
        default=None,
        metavar="KIND:SEED",
        help="only compare the internal_damping candidate at 0 and 1 hidden node on PyElastica's "
        "planted internal damping and its control (JSON rows), e.g. light:0 stiff:0",
    )
    p.add_argument(
        "--growing-windows",
        nargs="*",
        default=None,
        metavar="KIND:SEED",
        help="only compare the internal_damping candidate (and its reference) fitted on fixed and on "
        "growing windows (FitBudget.final_horizon) on PyElastica's planted internal damping and its "
        "control (JSON rows), e.g. stiff:0 light:1",
    )
    p.add_argument(
        "--own-resolution",
        type=int,
        nargs="*",
        default=None,
        metavar="SEED",
        help="only compare internal_damping and stiffness_variation fitted at 0 and 1 hidden node on the "
        "own simulator's planted internal damping and its control, each resolution with its own "
        "nominal fit (JSON rows)",
    )
    p.add_argument(
        "--fits-version",
        type=int,
        default=None,
        help=f"rows of this version of the fits (default {TOOL_VERSION}, today's); with --summary-only, "
        "re-decides stored rows of an older version with today's rule",
    )
    p.add_argument(
        "--refit",
        nargs="*",
        default=None,
        metavar="TERM",
        help="rows of the previous fits version: refit only these round-1 candidates (the ones today's "
        "fits changed) and keep the rest (exact for the first name); datasets without such a row run in full",
    )
    p.add_argument(
        "--stem",
        default=None,
        help="name of the result files (default diagnose, diagnose.elastica, diagnose.mujoco)",
    )
    p.add_argument(
        "--step-scan",
        nargs="*",
        default=None,
        metavar="KIND:SEED",
        help="only the check error of the internal_damping term at fixed sizes with the model stepped at "
        "10, 5 and 2.5 ms, on --simulator's planted internal damping and its control (JSON rows)",
    )
    p.add_argument(
        "--fine-nominal",
        nargs="*",
        default=None,
        metavar="SIM:KIND:EFFECT:SEED",
        help="only the internal_damping candidate at 5 ms against references from the 10 ms and from a "
        "5 ms nominal fit (JSON rows), e.g. own:-:none:1 elastica:light:internal_damping:0",
    )
    p.add_argument(
        "--full-size-timing",
        action="store_true",
        help="only time `deform diagnose` (full budget) on one elastica case of 8 + 4 x 500 frames",
    )
    p.add_argument(
        "--calibrate-damping",
        action="store_true",
        help="only fit the nominal model on independent-simulator controls and derive its material damping level",
    )
    args = p.parse_args()
    if args.full_size_timing:
        sys.path.insert(0, str(ROOT))
        print(json.dumps(full_size_timing(args)))
        return
    if args.calibrate_damping:
        torch.set_num_threads(1)
        sys.path.insert(0, str(ROOT))
        print(json.dumps(calibrate_damping(args)))
        return
    if args.hidden_damping is not None or args.growing_windows is not None:
        torch.set_num_threads(1)
        for item in args.hidden_damping or []:
            kind, seed = item.split(":")
            damping_study(kind, int(seed), args)
        for item in args.growing_windows or []:
            kind, seed = item.split(":")
            damping_study(kind, int(seed), args, variants=((0, None), (0, CHECK_HORIZON)))
        return
    if args.fine_nominal is not None:
        torch.set_num_threads(1)
        sys.path.insert(0, str(ROOT))
        for job in args.fine_nominal:
            fine_nominal_study(job, args)
        return
    if args.step_scan is not None:
        torch.set_num_threads(1)
        sys.path.insert(0, str(ROOT))
        for item in args.step_scan:
            kind, seed = item.split(":")
            step_scan(kind, int(seed), args, simulator=args.simulator)
        return
    if args.own_resolution is not None:
        torch.set_num_threads(1)
        for seed in args.own_resolution:
            own_resolution_study(seed, args)
        return
    if args.hidden_nodes is not None:
        torch.set_num_threads(1)
        for seed in args.hidden_nodes:
            hidden_nodes_study(seed, args)
        return
    if args.mass_equivalence is not None or args.damping_scan is not None:
        torch.set_num_threads(1)
        for seed in args.mass_equivalence or []:
            print(json.dumps(mass_equivalence(seed, args)), flush=True)
        if args.damping_scan is not None:
            damping_scan(args.damping_scan, args)
        return
    if args.smoke:
        args.quick = "smoke"
    torch.set_num_threads(1)
    stem = args.stem or ("diagnose" if args.simulator == "own" else f"diagnose.{args.simulator}")
    runs_path = Path(args.runs or RESULTS / f"{stem}.runs.jsonl")
    runs_path.parent.mkdir(exist_ok=True)
    done = load_runs(runs_path, _config(args))
    if args.simulator in INDEPENDENT:
        sys.path.insert(0, str(ROOT))
        independent_effects, _, _ = independent_simulator(args.simulator)

        effects = [e for e in (args.effects or independent_effects) if e != "none"]
        # per rod kind and seed: the control first (it is also the effects' pair), then the effects
        jobs = [
            (k, e, s)
            for k in args.rod_kinds
            for s in range(args.first_seed, max(args.seeds, args.control_seeds))
            for e in ([None] if s < args.control_seeds else []) + (effects if s < args.seeds else [])
        ]
        if not args.summary_only:
            run_independent(jobs, args, runs_path, done, args.simulator)
    else:
        effects = [e for e in (args.effects or EFFECTS) if e != "none"]
        # controls first (they calibrate the rule), then each seed through all effects, then the real rods
        jobs = [(None, s) for s in range(args.control_seeds)] + [
            (e, s) for s in range(args.seeds) for e in effects
        ]
        if not args.summary_only:
            run_planted(jobs, args, runs_path, done)
            run_real(args.real, args, runs_path, done)
    # rows another process appended since this one last looked: the tables are written from all of
    # them (two processes sharing a runs file each wrote tables missing the other's last rows)
    done.update(load_runs(runs_path, _config(args)))
    planted = [r for r in done.values() if r["kind"] == "planted"]
    planted.sort(key=lambda r: (r["effect"] != "none", r["effect"], r["seed"]))
    real = sorted((r for r in done.values() if r["kind"] == "real"), key=lambda r: r["rod"])
    rules = apply_rules(planted, real, args.alpha)
    b = budget(args.quick)
    result = {
        "command": "python benchmarks/diagnose_planted.py "
        + " ".join(a for a in sys.argv[1:] if a != "--summary-only"),
        "simulator": args.simulator,
        **provenance(),
        "budget": (
            f"nominal {b.nominal_iterations} Adam iterations, candidates {b.candidate.iterations} iterations "
            f"of {b.candidate.batch} windows x {b.candidate.horizon} steps, {b.max_rounds} rounds; "
            f"{args.fit} fit + {args.check} check recordings of {args.frames} frames per planted dataset "
            f"(real rods: the first {args.fit} + next {args.check} train recordings, full length)"
        ),
        "seconds_total_runs": float(sum(r["seconds"] for r in done.values())),
        "runs_file": runs_path.name,
        "rules": rules,
        "rule": RULE,
        "fits_of_tool_version": args.fits_version or TOOL_VERSION,
        "summary": {
            "tool": summarise(planted, "tool"),
            "as_run": summarise(planted, "as_run"),
            "calibrated": summarise(planted, "calibrated"),
        },
        "planted": planted,
        "real": real,
        "diverged": sorted((r for r in done.values() if r["kind"] == "diverged"), key=lambda r: r["key"]),
    }
    write(result, stem)


if __name__ == "__main__":
    main()
