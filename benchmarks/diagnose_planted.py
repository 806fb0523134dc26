"""Benchmark of `deform diagnose` on datasets with one planted effect (and controls), then on the
real recordings DLO1..DLO5 against plain DER.

Planted data: deform.diagnose.planted (finer rod, smaller dt, markers a subset of nodes, 0.3 mm
noise, gripper motions replayed from real DLO2 recordings). The tool is not told the effect.
Writes benchmarks/results/diagnose.{json,md}.

    python benchmarks/diagnose_planted.py [--quick] [--seeds 3] [--effects a b ...] [--real DLO1 ...]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from deform.diagnose.fitting import FitBudget
from deform.diagnose.planted import EFFECTS, generate_planted
from deform.diagnose.selection import DiagnoseBudget, diagnose
from deform.diagnose.spec import Inputs, RodSpec, load_inputs
from deform.io.recordings import find_data_root, load_recordings

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results"
RODS = {"DLO1": (1.152, 0.0345, 13), "DLO2": (0.996, 0.0652, 12), "DLO3": (0.998, 0.0968, 12),
        "DLO4": (0.973, 0.022, 12), "DLO5": (0.988, 0.0192, 12)}


def budget(quick: bool) -> DiagnoseBudget:
    if quick:
        return DiagnoseBudget(nominal_iterations=40, candidate=FitBudget(iterations=25, batch=12, horizon=25),
                              max_rounds=2, later_round_candidates=3, progress=False)
    return DiagnoseBudget(progress=False)


def param_error(found: dict, truth: dict) -> dict:
    out = {}
    for k, v in truth.items():
        key = k.replace("_per_m", "_per_vertex") if k.startswith("kappa") else k
        if key in found and v != 0:
            out[k] = abs(found[key] - v) / abs(v)
    return out


def run_planted(effects, seeds, quick, n_fit, n_check, frames) -> list[dict]:
    data = find_data_root()
    sources = load_recordings(data / "DLO2" / "train")
    L, M, n = RODS["DLO2"]
    spec = RodSpec(length_m=L, mass_kg=M, n_vertices=n, name="DLO2-planted")
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        pick = rng.choice(len(sources), n_fit + n_check, replace=False)
        src = [sources[i] for i in pick]
        for effect in effects:
            t0 = time.perf_counter()
            recs, truth = generate_planted(effect, src, spec, n_frames=frames, seed=seed)
            inputs = Inputs(spec=spec, fit=recs[:n_fit], check=recs[n_fit:])
            diag = diagnose(inputs, budget(quick))
            rep = diag.report
            sel = rep["selected"]
            found = next((c["params"] for c in rep["candidates"] if c["name"] == effect and c["round"] == 1), {})
            row = {"effect": effect or "none", "seed": seed, "selected": sel,
                   "detected": (sel[:1] == [effect]) if effect else (sel == []),
                   "exact": (sel == [effect]) if effect else (sel == []),
                   "truth": truth, "found": found, "param_rel_error": param_error(found, truth),
                   "nominal_check_l1_m": rep["nominal"]["check_l1_m"], "final_check_l1_m": rep["final_check_l1_m"],
                   "round1": {c["name"]: round(c["improvement"], 4) for c in rep["candidates"] if c["round"] == 1},
                   "seconds": time.perf_counter() - t0}
            rows.append(row)
            print(json.dumps({k: row[k] for k in ("effect", "seed", "selected", "nominal_check_l1_m", "final_check_l1_m", "seconds")}), flush=True)
    # gap closed: the control of the same seed (same grips, no effect) is the model class's floor
    floor = {r["seed"]: r["nominal_check_l1_m"] for r in rows if r["effect"] == "none"}
    for r in rows:
        if r["effect"] != "none" and r["seed"] in floor:
            gap = r["nominal_check_l1_m"] - floor[r["seed"]]
            r["gap_m"] = gap
            r["gap_closed"] = (r["nominal_check_l1_m"] - r["final_check_l1_m"]) / gap if gap > 1e-5 else None
    return rows


def run_real(rods, quick, n_fit, n_check) -> list[dict]:
    data = find_data_root()
    rows = []
    for rod in rods:
        L, M, n = RODS[rod]
        recs = load_recordings(data / rod / "train")
        spec = RodSpec(length_m=L, mass_kg=M, n_vertices=n, name=rod)
        inputs = Inputs(spec=spec, fit=recs[:n_fit], check=recs[n_fit:n_fit + n_check])
        t0 = time.perf_counter()
        rep = diagnose(inputs, budget(quick)).report
        rows.append({"rod": rod, "selected": rep["selected"], "nominal_check_l1_m": rep["nominal"]["check_l1_m"],
                     "final_check_l1_m": rep["final_check_l1_m"], "findings": rep["localization"]["findings"],
                     "final_params": rep["nominal"]["final_params"],
                     "round1": {c["name"]: round(c["improvement"], 4) for c in rep["candidates"] if c["round"] == 1},
                     "seconds": time.perf_counter() - t0})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def summarise(rows: list[dict]) -> dict:
    out = {}
    for eff in sorted({r["effect"] for r in rows}):
        rs = [r for r in rows if r["effect"] == eff]
        gaps = [r["gap_closed"] for r in rs if r.get("gap_closed") is not None]
        perr = [np.mean(list(r["param_rel_error"].values())) for r in rs if r["param_rel_error"]]
        out[eff] = {"runs": len(rs), "detection_rate": float(np.mean([r["detected"] for r in rs])),
                    "nominal_check_cm": float(np.mean([r["nominal_check_l1_m"] for r in rs]) * 100),
                    "final_check_cm": float(np.mean([r["final_check_l1_m"] for r in rs]) * 100),
                    "gap_closed_median": float(np.median(gaps)) if gaps else None,
                    "param_rel_error_median": float(np.median(perr)) if perr else None}
    return out


def write(result: dict) -> None:
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "diagnose.json").write_text(json.dumps(result, indent=2))
    lines = ["# deform diagnose: planted-effect benchmark", "", f"Run: `{result['command']}` on {result['machine']}; "
             f"{result['seconds']:.0f} s total.", "",
             "| planted effect | runs | named first | check before [cm] | after [cm] | gap closed (median) | param rel. error (median) |",
             "|---|---|---|---|---|---|---|"]
    for eff, s in result["summary"].items():
        gap = "-" if s["gap_closed_median"] is None else f"{s['gap_closed_median'] * 100:.0f} %"
        pe = "-" if s["param_rel_error_median"] is None else f"{s['param_rel_error_median'] * 100:.0f} %"
        lines.append(f"| {eff} | {s['runs']} | {s['detection_rate'] * 100:.0f} % | {s['nominal_check_cm']:.3f} | "
                     f"{s['final_check_cm']:.3f} | {gap} | {pe} |")
    lines += ["", "Per run (selected terms):", ""]
    for r in result["planted"]:
        lines.append(f"- {r['effect']} seed {r['seed']}: selected {r['selected'] or ['none']}, "
                     f"{r['nominal_check_l1_m'] * 100:.3f} -> {r['final_check_l1_m'] * 100:.3f} cm, {r['seconds']:.0f} s")
    if result["real"]:
        lines += ["", "## Real recordings against plain DER", "", "| rod | selected | check before [cm] | after [cm] | s |", "|---|---|---|---|---|"]
        for r in result["real"]:
            lines.append(f"| {r['rod']} | {', '.join(r['selected']) or 'none'} | {r['nominal_check_l1_m'] * 100:.3f} | "
                         f"{r['final_check_l1_m'] * 100:.3f} | {r['seconds']:.0f} |")
    (RESULTS / "diagnose.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    import sys

    p = argparse.ArgumentParser()
    p.add_argument("--quick", action="store_true")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--effects", nargs="*", default=None)
    p.add_argument("--real", nargs="*", default=list(RODS))
    p.add_argument("--fit", type=int, default=8)
    p.add_argument("--check", type=int, default=4)
    p.add_argument("--frames", type=int, default=500)
    args = p.parse_args()
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    effects = [None] + [e for e in (args.effects or EFFECTS) if e != "none"]
    planted = run_planted(effects, list(range(args.seeds)), args.quick, args.fit, args.check, args.frames) if args.seeds else []
    result = {"command": "python benchmarks/diagnose_planted.py " + " ".join(sys.argv[1:]),
              "machine": "2 CPU cores shared with other jobs, torch 1 thread", "seconds": time.perf_counter() - t0,
              "summary": summarise(planted), "planted": planted, "real": []}
    write(result)  # the planted part survives an interrupted real part
    result["real"] = run_real(args.real, args.quick, args.fit, args.check)
    result["seconds"] = time.perf_counter() - t0
    write(result)


if __name__ == "__main__":
    main()
