"""Stiff and short ropes at the 10 ms step: does a bent, held rope come to rest?

Each rope (12 vertices, straight at first) has its grippers brought 30 % of its length closer over
0.5 s, a little sideways, and held for 2.5 s; the row gives the top vertex speed over the last 0.5 s
with the bending stepped explicitly, implicitly (``deform.rod.implicit``) at one step a frame, and as
the model steps it (``chosen``: a shipped model's own scheme; for the others what a model whose
stiffness is being chosen gets, implicit above a step ratio of 1 and in substeps above
``IMPLICIT_RATIO_MAX``), and the explicit step's margin ``omega_max dt`` per frame (``step_ratio``). A rope at rest is below a few cm/s; one
that rings keeps metres a second. Ropes: the five shipped models as they are (their residual network
included), the generic DER (``deform.generic_model``) of 0.3-1.5 m, and 1 m ropes of 20-100 g at
stiffnesses from 0.001 to 0.1 N m^2 (cables). Also the cost of one frame, eager and compiled, implicit
and in two substeps over explicit (medians over many steps, the same run).

    python benchmarks/bending_stability.py   -> benchmarks/results/bending_stability.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

if not __package__:  # run as `python benchmarks/bending_stability.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.provenance import provenance
from deform import DeformModel, ModelOptions, generic_model, load_model
from deform.compiled import CompiledStep
from deform.config import generic_rod
from deform.step_graph import rod_at_rest

OUT = Path(__file__).resolve().parent / "results"
BEND = 0.3  # of the length
BEND_S, HOLD_S, TAIL_S = 0.5, 2.5, 0.5


def top_speed_after_bend(model: DeformModel) -> float:
    """Top vertex speed [m/s] over the last ``TAIL_S`` of the hold (inf when the state blew up)."""
    state, grip = rod_at_rest(model, 1, torch.float64)
    far = torch.zeros_like(grip)
    far[:, 2:, 0] = -BEND * float(state.rest.sum())
    far[:, 2:, 1] = 0.02
    steps, bend, tail = (round(s / model.dt) for s in (BEND_S + HOLD_S, BEND_S, TAIL_S))
    top = 0.0
    with torch.no_grad():
        for k in range(1, steps + 1):
            state = model.step(state, grip + min(k / bend, 1.0) * far)
            if k > steps - tail:
                speed = float(state.v.norm(dim=-1).amax())
                top = max(top, speed if np.isfinite(speed) else float("inf"))
    return top


def schemes(model: DeformModel, choose: bool) -> dict:
    """The top speed stepped explicitly, implicitly (one step a frame), and as the model steps it:
    its own scheme (``choose=False``: a shipped model) or what :meth:`choose_bending_scheme` gives a
    model whose stiffness is being chosen (implicit above a ratio of 1, in substeps above
    ``IMPLICIT_RATIO_MAX``)."""
    ratio = model.bending_step_ratio()
    if choose:
        model.choose_bending_scheme()
    chosen = (model.cfg.implicit_bending, model.cfg.substeps)
    out = {"step_ratio": ratio, "chosen_implicit": chosen[0], "chosen_substeps": chosen[1]}
    for implicit in (False, True):
        model.cfg.implicit_bending, model.cfg.substeps = implicit, 1
        out["implicit_m_per_s" if implicit else "explicit_m_per_s"] = top_speed_after_bend(model)
    model.cfg.implicit_bending, model.cfg.substeps = chosen
    same = "implicit_m_per_s" if chosen[0] else "explicit_m_per_s"
    out["chosen_m_per_s"] = out[same] if chosen[1] == 1 else top_speed_after_bend(model)
    return out


SCHEMES = {"explicit": (False, 1), "implicit": (True, 1), "substeps2": (True, 2)}  # (implicit, substeps)


def step_cost(steps: int = 2000) -> dict:
    """Median and p99 of one frame's step [ms], eager and compiled (branch-free, ahead of time as
    the service runs it), for a 1 m 50 g generic rope stepped explicitly, implicitly and implicitly
    in two substeps."""
    out = {}
    for scheme, (implicit, substeps) in SCHEMES.items():
        model = generic_model(1.0, 0.05)
        model.cfg.implicit_bending, model.cfg.substeps = implicit, substeps
        model.options.residual = True  # the service's models carry the network
        for mode in ("eager", "compiled"):
            step = (
                CompiledStep(model, branch_free=(4, 4), ahead_of_time=True)
                if mode == "compiled"
                else model.step
            )
            state, grip = rod_at_rest(model, 1, torch.float64)
            times = []
            with torch.no_grad():
                for k in range(steps + 200):
                    g = grip.clone()
                    g[:, 2:, 2] += 0.1 * np.sin(k / 30)
                    t0 = time.perf_counter()
                    state = step(state, g)
                    times.append(time.perf_counter() - t0)
            t = np.array(times[200:]) * 1e3
            out[f"{mode}_{scheme}"] = {"p50_ms": float(np.median(t)), "p99_ms": float(np.percentile(t, 99))}
    for mode in ("eager", "compiled"):
        for scheme in ("implicit", "substeps2"):
            ratio = out[f"{mode}_{scheme}"]["p50_ms"] / out[f"{mode}_explicit"]["p50_ms"]
            out[f"{mode}_{'ratio' if scheme == 'implicit' else 'substeps2_ratio'}_p50"] = ratio
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, default=OUT / "bending_stability.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cases: list[tuple[str, dict, callable]] = []
    for rod in ("DLO1", "DLO2", "DLO3", "DLO4", "DLO5"):
        cases.append((f"{rod} (shipped)", {"rod": rod}, lambda rod=rod: load_model(rod).eval()))
    for length in (0.3, 0.5, 0.75, 1.0, 1.5):
        cases.append(
            (
                f"generic {length:g} m, 50 g",
                {"length_m": length, "mass_kg": 0.05},
                lambda length=length: generic_model(length, 0.05),
            )
        )
    for ei in (0.001, 0.003, 0.01, 0.03, 0.1):
        for mass in (0.02, 0.05, 0.1):

            def build(ei=ei, mass=mass):
                cfg = generic_rod(1.0, mass, 12).model_copy(
                    update=dict(bend_stiffness=ei, twist_stiffness=0.7 * ei)
                )
                return DeformModel(cfg, ModelOptions(residual=False)).eval()

            cases.append(
                (
                    f"1 m, {mass * 1e3:g} g, EI {ei:g}",
                    {"length_m": 1.0, "mass_kg": mass, "bend_stiffness_Nm2": ei},
                    build,
                )
            )
    rows = []
    for name, spec, build in tqdm(cases, desc="ropes bent and held"):
        rows.append({"rope": name, **spec, **schemes(build(), choose=not spec.get("rod"))})
    cost = step_cost()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({**provenance(argv), "rows": rows, "step_cost": cost}, indent=2) + "\n")
    for r in rows:
        print(
            f"{r['rope']:28s} ratio {r['step_ratio']:5.2f}  explicit {r['explicit_m_per_s']:8.3f}  "
            f"implicit {r['implicit_m_per_s']:8.3f}  chosen {r['chosen_m_per_s']:8.3f} m/s "
            f"({'implicit' if r['chosen_implicit'] else 'explicit'}, {r['chosen_substeps']} substeps)"
        )
    print(json.dumps(cost, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
