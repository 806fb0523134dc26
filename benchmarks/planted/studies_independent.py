"""Studies on the independent simulators' planted data and the nominal model (each a
``benchmarks/diagnose_planted.py`` option; none is part of the benchmark's tables): the material
damping level from controls (``--calibrate-damping``), a full-size run's wall time
(``--full-size-timing``), internal damping at a finer resolution or on growing windows
(``--hidden-damping``, ``--growing-windows``), the model's own step (``--step-scan``) and a nominal
model fitted at 5 ms (``--fine-nominal``)."""

from __future__ import annotations

import copy
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.planted.config import SLOW_STEP_S, budget
from benchmarks.planted.inputs import as_user_inputs, independent_simulator
from benchmarks.planted.tables import RESULTS
from benchmarks.provenance import provenance
from benchmarks.rods import data_root, independent_rod, own_dataset_sources, seeded_sources
from benchmarks.store import RunStore, write_atomic
from deform.diagnose.planted import generate_planted
from deform.diagnose.simulator import CHECK_HORIZON
from deform.diagnose.spec import Inputs

REPO = Path(__file__).resolve().parents[2]
SCRIPT = "benchmarks/diagnose_planted.py"


def calibrate_damping(args) -> dict:
    """The nominal model's material damping level (deform.terms.library.MATERIAL_DAMPING_LEVEL) from
    controls only (no effect planted): the linear damping a free nominal fit gives on
    independent-simulator controls (light and stiff rod, small material damping) and on this
    project's own controls (stored rows); the level = 2x the largest. The factor leaves room for
    ropes damped more than these; drag and contact have measured 5-10x."""
    from benchmarks.planted.elastica import generate_elastica
    from deform.diagnose.fitting import coarse_nominal, fit
    from deform.diagnose.simulator import Nominal, Simulator

    data = data_root()
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
    own = RunStore.for_runs(RESULTS / "diagnose.runs").load(
        {"quick": True, "fit": 6, "check": 4, "frames": 300, "tool": 2}
    )
    fitted += [
        {"simulator": "own", "seed": r["seed"], **r["nominal_params"]}
        for r in own.values()
        if r["kind"] == "planted" and r["effect"] == "none"
    ]
    worst = max(f["damping_1_per_s"] for f in fitted)
    out = {
        **provenance(["--calibrate-damping", "--rod-kinds", *args.rod_kinds], script=SCRIPT),
        "controls": fitted,
        "largest_1_per_s": worst,
        "level_1_per_s": round(2 * worst, 2),
    }
    write_atomic(RESULTS / "diagnose.damping_level.json", json.dumps(out, indent=2))
    return out


def full_size_timing(args) -> dict:
    """Wall time of `deform diagnose` with the default (full) budget on one independent-simulator case
    of the issue's size (8 + 4 recordings of 500 frames), run as a user runs it: files on disk and
    the command line, with the default workers (the cores) and, as the same run's baseline, one.
    ``--cold-compile``: each run with an empty inductor cache, as a machine's first run.
    -> the row stored in benchmarks/results/diagnose.timing.EFFECT[.cold].json."""
    import os
    import subprocess
    import tempfile

    from benchmarks.planted.elastica import generate_elastica
    from deform.cores import available_cores
    from deform.io import save_recording

    kind, effect = args.rod_kinds[0], (args.effects or ["ground_contact"])[0]
    cold = args.cold_compile
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
            "--json",
        ]
        runs = {}
        # as a user runs it (default workers: the cores), then one process as the same run's baseline
        for label, extra in (("default", []), ("one_worker", ["--workers", "1"])):
            env = dict(os.environ)
            if cold:  # the first run on a machine: nothing compiled yet (deform/rod/fusion.py)
                env["TORCHINDUCTOR_CACHE_DIR"] = str(tmp / f"inductor_{label}")
            load = os.getloadavg()[0]
            t0 = time.perf_counter()
            out = subprocess.run(
                [*cmd, "--out", str(tmp / f"out_{label}"), *extra],
                capture_output=True,
                text=True,
                cwd=REPO,
                env=env,
            )
            runs[label] = {
                "seconds_wall": time.perf_counter() - t0,
                "load_average_1min_at_start": load,
                "returncode": out.returncode,
                "selected": (json.loads(out.stdout) if out.returncode == 0 else {}).get("selected"),
                "stderr_tail": out.stderr[-300:] if out.returncode else "",
            }
    d, one = runs["default"], runs["one_worker"]
    row = {
        **provenance(
            [
                "--full-size-timing",
                "--rod-kinds",
                kind,
                "--effects",
                effect,
                *(["--cold-compile"] if cold else []),
            ],
            script=SCRIPT,
        ),
        "inductor_cache": "empty at each run's start" if cold else "as left by earlier runs",
        "case": f"elastica {kind} {effect} seed 0, 8 + 4 recordings x 500 frames",
        "budget": "full (default)",
        "workers_default": available_cores(),
        "seconds_wall": d["seconds_wall"],
        "returncode": d["returncode"],
        "selected": d["selected"],
        "seconds_wall_one_worker": one["seconds_wall"],
        "speedup_over_one_worker": one["seconds_wall"] / d["seconds_wall"],
        "same_names": d["selected"] == one["selected"],
        "runs": runs,
    }
    write_atomic(
        RESULTS / f"diagnose.timing.{effect}{'.cold' if cold else ''}.json", json.dumps(row, indent=2)
    )
    return row


def damping_study(kind: str, seed: int, args, variants=((0, None), (1, None))) -> list[dict]:
    """Would another fit see PyElastica's internal damping? On the planted dataset and its paired
    control (same motions and noise), the nominal fit at marker resolution, then per variant
    ``(hidden, final_horizon)`` a reference refit and the internal_damping candidate (same budget,
    scored on the windowed check error as the tool scores candidates): ``hidden`` nodes per marker
    interval (--hidden-damping), fit windows growing to ``final_horizon`` steps (--growing-windows)."""
    from benchmarks.planted.elastica import generate_elastica
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
        src, spec = own_dataset_sources(seed, 10)
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
