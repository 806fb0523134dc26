"""Studies on the own simulator's planted data (each a ``benchmarks/diagnose_planted.py`` option that
prints JSON rows; none is part of the benchmark's tables): how much of a marker mass is a uniform
mass (``--mass-equivalence``), the internal-damping term swept with the nominal model held
(``--damping-scan``), a finer tool model on marker masses (``--hidden-nodes``) and on internal
damping (``--own-resolution``)."""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import torch

from benchmarks.planted.config import budget
from benchmarks.planted.inputs import marker_edge
from benchmarks.provenance import provenance
from benchmarks.rods import own_dataset_sources
from deform.diagnose.planted import generate_planted, oracle_term
from deform.diagnose.simulator import CHECK_HORIZON
from deform.diagnose.spec import Inputs, RodSpec
from deform.model import gripped_indices


def mass_equivalence(seed: int, args) -> dict:
    """How much of the planted marker mass is a uniform mass factor (= stiffness / s, unobservable when
    stiffness is fitted): the planted data against (a) the control and (b) the control with EI and GJ
    divided by s, s = (free rod mass + marker masses) / free rod mass; same motions, same noise."""
    from deform.diagnose.planted import _layout

    src, spec = own_dataset_sources(seed, args.fit + args.check)
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

    src, spec = own_dataset_sources(seed, args.fit + args.check)
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

    src, spec = own_dataset_sources(seed, args.fit + args.check)
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

    src, spec = own_dataset_sources(seed, args.fit + args.check)
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
