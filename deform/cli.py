"""`deform` command line: train, eval, bench, demo, calibrate.

Errors on bad input are one line on stderr naming the file and the problem, exit code 2, and
nothing is written.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from deform.argtypes import int_at_least, number
from deform.config import ConfigError
from deform.errors import CheckpointError, UsageError
from deform.io.gaps import MAX_GAP_S
from deform.io.recordings import RecordingError, find_data_root

# set for the calibrate program ``deform calibrate`` starts: its --time-limit counts this process's
# start too (read by calibrate.cli, which may import deform; deform may not import calibrate)
CALIBRATE_CLOCK_ENV = "DEFORM_CALIBRATE_CLOCK_FROM_PARENT"


def _data_dir(rod: str, split: str, explicit: str | None) -> Path:
    if explicit:
        return Path(explicit)
    root = find_data_root()
    if root is None:
        raise UsageError("no dataset found: set DEFORM_DATA or pass --recordings")
    return root / rod / split


def cmd_train(args) -> int:
    """``deform train``: train (or fine-tune with ``--init``) a rod's model; ``--install`` ships it.

    Args:
        args: the parsed command line.

    Returns:
        The exit code (errors are raised and reported by :func:`main` as one line, exit code 2).
    """
    import torch

    from deform.config import load_rod_config
    from deform.io.gaps import fill_recordings
    from deform.io.labels import fix_recordings_labels
    from deform.io.orientation import check_up_axis
    from deform.io.recordings import load_recordings
    from deform.model import MODEL_DIR, DeformModel, ModelOptions, load_model
    from deform.train import TrainConfig, split_validation, train

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)  # the residual network's initial weights
    from deform.terms import check_names, describe

    check_names(args.term + args.without)  # before any data is read
    for name in args.term:
        print(describe(name), file=sys.stderr)
    cfg = load_rod_config(args.rod)
    recs = load_recordings(_data_dir(args.rod, "train", args.recordings), cfg.n_vertices, allow_gaps=True)
    recs, gap_note = fill_recordings(recs, args.max_gap, dt=cfg.dt)
    recs, label_note = fix_recordings_labels(recs)
    up_note = check_up_axis(recs, args.recordings or args.rod)
    for note in (gap_note, label_note, up_note):
        if note:
            print(f"note: {note}", file=sys.stderr)
    train_recs, val_recs = split_validation(recs, args.val_every)
    if not train_recs:
        raise UsageError(f"{args.recordings}: too few recordings to train")
    options = ModelOptions(
        residual=not args.no_residual,
        weighted_pbd=not args.original_inextensibility,
        theta_solver=args.theta_solver,
    )
    model = load_model(args.init) if args.init else DeformModel(cfg, options)
    model.options = options
    tcfg = TrainConfig(
        iterations=args.iterations,
        batch=args.batch,
        horizon=args.horizon,
        residual=not args.no_residual,
        sysid=not args.no_sysid,
        seed=args.seed,
        time_limit_s=args.time_limit,
        curriculum=tuple(args.curriculum) if args.horizon > 1 else (),
        lr_physics=args.lr_physics,
        lr_network=args.lr_network,
        coarse_sysid=not args.init,  # a given starting model is already identified
        bending=args.bending,
        drag=not args.no_drag,
        terms=tuple(args.term),
        without=tuple(args.without),
        transported_frames=not args.fresh_frames,
    )
    out = Path(args.out or f"runs/{args.rod}")
    result = train(model, train_recs, val_recs, tcfg, out, resume=not args.fresh)
    best = DeformModel.load(out / "best.pt")
    if args.install:
        best.save(MODEL_DIR / f"{args.rod}.pt")
    print(json.dumps({"rod": args.rod, "out": str(out), **result}))
    return 0


def cmd_eval(args) -> int:
    """``deform eval``: the paper's metric on a directory of recordings, DEFORM or a baseline.

    Args:
        args: the parsed command line.

    Returns:
        The exit code (errors are raised and reported by :func:`main` as one line, exit code 2).
    """
    import torch

    from deform.evaluate import evaluate
    from deform.io.recordings import load_recordings
    from deform.model import load_model

    torch.set_num_threads(args.threads)
    if args.rod is None and (args.method != "deform" or not (args.model and args.recordings)):
        raise UsageError("eval needs --rod, or --model and --recordings")
    if args.method == "deform":
        model = load_model(args.model or args.rod)
        if args.no_residual:
            model.options.residual = False
    else:
        from deform.baselines import load_baseline  # same interface: n, initial_state, step

        model = load_baseline(args.method, args.rod, args.model)
    directory = _data_dir(args.rod, "eval", args.recordings)
    recs = load_recordings(directory)  # other marker counts: compared by arc length (deform.evaluate)
    result = {
        "rod": args.rod or model.cfg.name,
        "method": args.method,
        "recordings_dir": str(directory),
        **evaluate(model, recs, args.steps),
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(
            f"{result['rod']}: L1 {result['l1_m'] * 100:.3f} cm over {result['recordings']} recordings, "
            f"{result['steps']} steps; step p50 {result['step_ms_p50']:.3f} ms"
        )
    return 0


def cmd_bench(args) -> int:
    """``deform bench``: the speed benchmark.

    Args:
        args: the parsed command line.

    Returns:
        The exit code (errors are raised and reported by :func:`main` as one line, exit code 2).
    """
    from deform.bench import run_benchmarks

    result = run_benchmarks(quick=args.quick)
    print(json.dumps(result, indent=2) if args.json else result)
    return 0


def cmd_diagnose(args) -> int:
    """``deform diagnose``: see :mod:`deform.diagnose`.

    Args:
        args: the parsed command line.

    Returns:
        The exit code (errors are raised and reported by :func:`main` as one line, exit code 2).
    """
    from deform.diagnose import run_cli

    return int(run_cli(args) or 0)


def cmd_demo(args) -> int:
    """``deform demo``: the service demo, or the model alone.

    Args:
        args: the parsed command line.

    Returns:
        The exit code (errors are raised and reported by :func:`main` as one line, exit code 2).
    """
    import importlib.util

    # the service is a layer above the model: its demo runs as a program of its own, not an import
    if not args.model_only and importlib.util.find_spec("service") is not None:
        import subprocess
        import sys

        return subprocess.call([sys.executable, "-m", "service.demo"])
    from deform.demo import main as model_demo

    return int(model_demo() or 0)


def cmd_calibrate(argv: list[str]) -> int:
    """``deform calibrate``: a model of a new rope from bags of camera clouds and gripper poses.

    The calibration package sits above the service (it decodes bags with the service's codecs), a
    layer above the model: it runs as a program of its own (``python -m calibrate``), not an import,
    as ``deform demo`` runs the service's demo. The child finds the package where this process does.

    Args:
        argv: the arguments after ``calibrate``, passed on unchanged.

    Returns:
        The program's exit code (2: bad input, one line on stderr, nothing written).
    """
    import importlib.util
    import os
    import subprocess

    spec = importlib.util.find_spec("calibrate")
    if spec is None or spec.origin is None:
        raise UsageError("the calibrate package is not installed (reinstall the project: pip install -e .)")
    env = dict(os.environ)
    root = str(Path(spec.origin).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    env[CALIBRATE_CLOCK_ENV] = "1"
    return subprocess.call([sys.executable, "-m", "calibrate", *argv], env=env)


def _add_max_gap(p: argparse.ArgumentParser) -> None:
    """``--max-gap``, the same for every command that reads a user's recordings (deform.io.gaps)."""
    p.add_argument(
        "--max-gap",
        type=number(positive=False),
        default=MAX_GAP_S,
        metavar="SECONDS",
        help="markers missing (NaN) for at most this long are filled by cubic splines in time and "
        "incomplete frames at a recording's ends dropped, stated as a note (default 0.1 s; "
        "0: any missing marker is an error)",
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="deform", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    t = sub.add_parser(
        "train", help="identify parameters and train the residual network on a rod's recordings"
    )
    t.add_argument("--rod", required=True)
    t.add_argument("--recordings", help="directory of .pkl (default: DATA/ROD/train)")
    _add_max_gap(t)
    t.add_argument("--out", help="run directory (default runs/ROD); resumes from its checkpoint")
    t.add_argument("--iterations", type=int_at_least(1), default=300)
    t.add_argument("--batch", type=int_at_least(1), default=32)
    t.add_argument("--horizon", type=int_at_least(1), default=100)
    t.add_argument("--curriculum", type=int_at_least(1), nargs="*", default=[10, 25, 50])
    t.add_argument("--time-limit", type=number(positive=True), default=None, help="seconds")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument(
        "--val-every", type=int_at_least(1), default=5, help="hold out every k-th recording for validation"
    )
    t.add_argument("--no-residual", action="store_true")
    t.add_argument("--no-sysid", action="store_true")
    t.add_argument("--original-inextensibility", action="store_true")
    t.add_argument("--theta-solver", choices=["newton", "theseus"], default="newton")
    t.add_argument("--no-drag", action="store_true", help="no quadratic air drag (linear damping only)")
    t.add_argument(
        "--fresh-frames",
        action="store_true",
        help="start every training window in fresh space-parallel reference frames instead of "
        "the ones a rollout from the recording's start carries there",
    )
    t.add_argument(
        "--term",
        action="append",
        default=[],
        metavar="NAME",
        help="physics `deform diagnose` named, trained into the model (repeatable): internal_damping, "
        "ground_contact, external_force are added; aerodynamic_drag, stiffness_variation, rest_curvature, "
        "point_mass are already in DEFORM",
    )
    t.add_argument(
        "--without",
        action="append",
        default=[],
        metavar="NAME",
        help="ablation: train without a built-in term (aerodynamic_drag, stiffness_variation, "
        "rest_curvature, point_mass) or an added term the starting model carries",
    )
    t.add_argument("--init", help="start from this model (.pt or rod name); skips the coarse identification")
    t.add_argument(
        "--bending",
        choices=("auto", "explicit", "implicit"),
        default="auto",
        help="how the bending is stepped (docs/model.md): auto, the coarse identification chooses by the "
        "stiffest mode's turn per step (with --init, the starting model's scheme); or fixed",
    )
    t.add_argument("--lr-physics", type=number(positive=True), default=2e-2)
    t.add_argument("--lr-network", type=number(positive=True), default=1e-3)
    t.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint")
    t.add_argument("--install", action="store_true", help="copy the best model to deform/models/ROD.pt")
    t.add_argument("--threads", type=int_at_least(1), default=1)
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="500-step open-loop prediction of every recording in a directory")
    e.add_argument("--rod", help="a shipped rod (its model and eval recordings by default)")
    e.add_argument("--recordings", help="directory of .pkl (default: DATA/ROD/eval)")
    e.add_argument(
        "--model",
        help="checkpoint (.pt); default: the shipped model of the rod. Another vertex count than the "
        "markers': compared by arc length",
    )
    e.add_argument("--steps", type=int_at_least(1), default=500)
    e.add_argument("--no-residual", action="store_true")
    e.add_argument("--method", default="deform", help="deform (default) or a baseline: see deform.baselines")
    e.add_argument("--json", action="store_true")
    e.add_argument("--threads", type=int_at_least(1), default=1)
    e.set_defaults(func=cmd_eval)

    b = sub.add_parser("bench", help="speed benchmark (latency, throughput, scaling, training)")
    b.add_argument("--json", action="store_true")
    b.add_argument("--quick", action="store_true")
    b.set_defaults(func=cmd_bench)

    g = sub.add_parser(
        "diagnose", help="locate and name the physics a simulation leaves out (see deform.diagnose)"
    )
    g.add_argument(
        "--rod",
        required=True,
        help="ROD.json: length_m, mass_kg, n_vertices, dt (the frame period [s]; not 0.01: resampled to 100 Hz)",
    )
    g.add_argument("--fit", required=True, help="directory of recordings to fit")
    g.add_argument("--check", required=True, help="directory of held-out recordings")
    g.add_argument("--out", required=True, help="output directory (report.json, report.md, plots)")
    g.add_argument("--model", help="starting model (.pt)")
    g.add_argument(
        "--budget",
        choices=("full", "quick"),
        default="full",
        help="fitting effort: full (default) or quick (about a third; the planted benchmark's)",
    )
    g.add_argument(
        "--clamp",
        default="fit",
        metavar="fit|METRES",
        help="how far past the gripped markers the grippers hold the rope: fit (default, fitted with "
        "the nominal model), or a known length in metres held fixed (0: the rope is free at the markers)",
    )
    g.add_argument(
        "--denoise",
        choices=("auto", "off"),
        default="auto",
        help="auto (default): recordings at 100 Hz or faster with marker noise above 0.5 mm are smoothed "
        "(Savitzky-Golay, stated in the report); off: never",
    )
    _add_max_gap(g)
    g.add_argument(
        "--workers",
        type=int_at_least(1),
        default=None,
        help="processes fitting a round's candidates side by side (default: the cores); the names "
        "and numbers do not depend on it",
    )
    g.add_argument("--json", action="store_true", help="print report.json")
    g.set_defaults(func=cmd_diagnose)

    c = sub.add_parser(
        "calibrate",
        add_help=False,
        help="a model of a new rope from bags of a robot moving it before an RGB-D camera, given its "
        "length and mass (deform calibrate --help)",
    )
    c.add_argument("args", nargs=argparse.REMAINDER)
    c.set_defaults(func=lambda args: cmd_calibrate(args.args))

    d = sub.add_parser("demo", help="the main job: the service on a demo replay (or the model demo)")
    d.add_argument("--model-only", action="store_true")
    d.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    """The ``deform`` command.

    Args:
        argv: arguments (None: ``sys.argv``).

    Returns:
        The exit code: 0, or 2 for bad input (one line on stderr, nothing written).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["calibrate"]:  # every argument, options included, belongs to the calibrate program
        try:
            return cmd_calibrate(argv[1:])
        except UsageError as exc:
            print(f"deform calibrate: error: {exc}", file=sys.stderr)
            return 2
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (RecordingError, ConfigError, UsageError, CheckpointError) as exc:
        print(f"deform {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
