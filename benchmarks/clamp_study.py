"""Does the PyElastica benchmark's clamp explain the stiffness variation named on held-out controls?

The independent-simulator benchmark (``benchmarks/planted/elastica.py``) holds each gripped portion out to
the next node of PyElastica's grid, up to a node (2.4 cm) past the gripped marker, while the tool's
model frees the rope right at that marker. On the light rod's held-out controls (seeds 3 and 5)
the tool named a softer middle, i.e. stiffer ends (docs/diagnose.md, held-out seeds). This runs
the same control twice, with the benchmark's clamps and with clamps ending at the node nearest the
gripped marker, and fits the nominal model and two candidates (the stiffness variation and, as a
comparison, wind) with the tool's quick budget. One JSON line per run, appended to
``benchmarks/results/diagnose.clamp_study.jsonl``.

    python benchmarks/clamp_study.py --rod-kind light --seeds 3 5 0 [--snap outward nearest]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

if not __package__:  # run as `python benchmarks/clamp_study.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.planted.config import budget as tool_budget
from benchmarks.planted.elastica import generate_elastica
from benchmarks.planted.inputs import as_user_inputs
from benchmarks.provenance import provenance
from benchmarks.rods import independent_rod, seeded_sources
from deform.diagnose.selection import diagnose

ROOT = Path(__file__).resolve().parent

CANDIDATES = ("stiffness_variation", "external_force")


def run(kind: str, seed: int, snap: str, args) -> dict:
    spec, sources = independent_rod(kind, None, "elastica")
    src = seeded_sources(sources, seed, args.fit + args.check)
    t0 = time.perf_counter()
    recs, truth = generate_elastica(
        None, src, spec, rod_kind=kind, n_frames=args.frames, seed=seed, grip_snap=snap
    )
    inputs = as_user_inputs(spec, recs[: args.fit], recs[args.fit :])
    # tool v8's nominal model, which frees the rope at the gripped markers: the study asks whether the
    # benchmark's clamp is what that model missed (tool v9 fits the clamp instead)
    budget = dataclasses.replace(
        tool_budget(True), candidates=CANDIDATES, max_rounds=1, progress=False, fit_clamp=False
    )
    rep = diagnose(inputs, budget).report
    return {
        "rod_kind": kind,
        "seed": seed,
        "grip_snap": snap,
        "held_s_m": truth["numerics"]["held_s_m"],
        "marker_s_m": [truth["rod"]["marker_s_m"][i] for i in (0, 1, -2, -1)],
        "nominal_params": rep["nominal"]["params"],
        "nominal_check_l1_m": rep["nominal"]["check_l1_m"],
        "candidates": [
            {
                "name": c["name"],
                "improvement": c["improvement"],
                "threshold": c["threshold"],
                "params": c["params"],
            }
            for c in rep["candidates"]
        ],
        "selected": rep["selected"],
        "seconds": time.perf_counter() - t0,
        **provenance(),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rod-kind", default="light", choices=("light", "stiff"))
    p.add_argument("--seeds", type=int, nargs="+", default=[3, 5, 0])
    p.add_argument("--snap", nargs="+", default=["outward", "nearest"], choices=("outward", "nearest"))
    p.add_argument("--fit", type=int, default=8)
    p.add_argument("--check", type=int, default=4)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--out", default=str(ROOT / "results" / "diagnose.clamp_study.jsonl"))
    args = p.parse_args()
    torch.set_num_threads(1)
    for seed in args.seeds:
        for snap in args.snap:
            row = run(args.rod_kind, seed, snap, args)
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")
            best = max(row["candidates"], key=lambda c: c["improvement"])
            print(
                f"{args.rod_kind} seed {seed} {snap}: EI {row['nominal_params']['bend_stiffness_Nm2']:.2e}, "
                f"check {row['nominal_check_l1_m'] * 100:.3f} cm, best {best['name']} "
                f"{best['improvement'] * 100:+.1f} %, selected {row['selected'] or ['none']}",
                flush=True,
            )


if __name__ == "__main__":
    main()
