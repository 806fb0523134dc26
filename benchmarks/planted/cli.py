"""The command line of the planted-effect benchmark (``python benchmarks/diagnose_planted.py``): the
benchmark itself (:func:`benchmarks.planted.run.run_benchmark`) or one of its studies."""

from __future__ import annotations

import argparse
import json

import torch

from benchmarks.cluster import add_arguments
from benchmarks.planted.config import TOOL_VERSION
from benchmarks.planted.inputs import INDEPENDENT
from benchmarks.planted.run import run_benchmark
from benchmarks.rods import DEFAULT_ROD_KINDS, RODS, SOURCE_ROD
from deform.diagnose.simulator import CHECK_HORIZON


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
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
        choices=list(SOURCE_ROD),
        help="elastica, mujoco: light (DLO1 motions), stiff (DLO3); medium (DLO2) only when asked",
    )
    p.add_argument(
        "--runs",
        default=None,
        help="the stored rows, one file per dataset (resumed): a directory, default "
        "benchmarks/results/<stem>.runs/ (rows of an old <stem>.runs.jsonl beside it are read too)",
    )
    p.add_argument(
        "--summary-only", action="store_true", help="only rebuild diagnose.{json,md} from the stored rows"
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
        "--names-against",
        default=None,
        metavar="STEM",
        help="compare the names of each dataset with those stored in results/STEM.json (same "
        "datasets, another run), and this run's wall time with that run's datasets fitted two at a time",
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
        "--cold-compile",
        action="store_true",
        help="with --full-size-timing: each run with an empty inductor cache, as the first run on a "
        "machine (-> diagnose.timing.EFFECT.cold.json)",
    )
    p.add_argument(
        "--calibrate-damping",
        action="store_true",
        help="only fit the nominal model on independent-simulator controls and derive its material damping level",
    )
    add_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    study = _study(args)
    if study is not None:
        torch.set_num_threads(1)
        study()
        return 0
    if args.smoke:
        args.quick = "smoke"
    return run_benchmark(args, argv=argv)


def _study(args):
    """The study an option asks for (it prints JSON rows; see the studies' modules), or None."""
    from benchmarks.planted import studies_independent as si
    from benchmarks.planted import studies_own as so

    if args.full_size_timing:
        return lambda: print(json.dumps(si.full_size_timing(args)))
    if args.calibrate_damping:
        return lambda: print(json.dumps(si.calibrate_damping(args)))
    if args.hidden_damping is not None or args.growing_windows is not None:

        def damping():
            for item in args.hidden_damping or []:
                kind, seed = item.split(":")
                si.damping_study(kind, int(seed), args)
            for item in args.growing_windows or []:
                kind, seed = item.split(":")
                si.damping_study(kind, int(seed), args, variants=((0, None), (0, CHECK_HORIZON)))

        return damping
    if args.fine_nominal is not None:
        return lambda: [si.fine_nominal_study(job, args) for job in args.fine_nominal]
    if args.step_scan is not None:

        def scan():
            for item in args.step_scan:
                kind, seed = item.split(":")
                si.step_scan(kind, int(seed), args, simulator=args.simulator)

        return scan
    if args.own_resolution is not None:
        return lambda: [so.own_resolution_study(seed, args) for seed in args.own_resolution]
    if args.hidden_nodes is not None:
        return lambda: [so.hidden_nodes_study(seed, args) for seed in args.hidden_nodes]
    if args.mass_equivalence is not None or args.damping_scan is not None:

        def mass():
            for seed in args.mass_equivalence or []:
                print(json.dumps(so.mass_equivalence(seed, args)), flush=True)
            if args.damping_scan is not None:
                so.damping_scan(args.damping_scan, args)

        return mass
    return None
