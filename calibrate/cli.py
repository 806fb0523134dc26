"""``deform calibrate`` (run as ``python -m calibrate``): a model of a new rope from bags of a robot
moving it in front of an RGB-D camera, with the rope's length and mass.

Bad input (a bag without gripper poses or clouds, a colour range that finds no rope, a length the
camera contradicts, unreadable settings) is one line on stderr, exit code 2, and nothing is written.
Clips too short or too still to identify anything get a report that says so, no model, and exit
code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

from calibrate.errors import CalibrationError
from deform.cli import CALIBRATE_CLOCK_ENV as CLOCK_FROM_PARENT

PROG = "deform calibrate"
MAX_START_AGE_S = 300.0  # an older start is not this command's (a parent gone: the process is then init's)


def process_started_at(pid: int | str = "self") -> float | None:
    """When process ``pid`` started, in :func:`time.time` seconds; None where ``/proc`` cannot tell.

    Why: ``--time-limit`` promises the whole command, and Python's start and the imports (torch and
    the model: 5-6 s on a busy 2-core machine, again in ``deform calibrate``'s parent) come before
    any line of this program runs. Read from ``/proc`` (Linux) rather than with a new dependency."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()  # after the name, which may hold spaces
        with open("/proc/uptime") as f:
            uptime_s = float(f.read().split()[0])
        age_s = uptime_s - int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22: start since boot
    except (OSError, ValueError, IndexError):
        return None
    return time.time() - age_s


def command_age_s() -> float:
    """Seconds since this command started: this process's start, or its parent's when ``deform
    calibrate`` started it (:data:`CLOCK_FROM_PARENT`); 0 where that cannot be told or is not
    within :data:`MAX_START_AGE_S`."""
    started = [process_started_at()]
    if os.environ.get(CLOCK_FROM_PARENT):
        started.append(process_started_at(os.getppid()))
    ages = [time.time() - t for t in started if t is not None]
    ages = [a for a in ages if 0.0 <= a <= MAX_START_AGE_S]
    return max(ages, default=0.0)


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number: {text!r}")
    return value


def _count(low: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be at least {low}: {text!r}")
        return value

    return parse


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    p.add_argument("bags", nargs="+", metavar="BAG", help="rosbag2 folders or .mcap files (one clip each)")
    p.add_argument(
        "--length",
        type=_positive,
        required=True,
        metavar="METRES",
        help="the rope's length between the grippers' grip points (what the model spans)",
    )
    p.add_argument(
        "--mass",
        type=_positive,
        required=True,
        metavar="KG",
        help="the mass of that length (weighed; a rope running on beyond the grippers: its share)",
    )
    p.add_argument(
        "--diameter",
        type=_positive,
        metavar="METRES",
        help="the rope's diameter: the camera sees its near surface, half of it in front of the centreline",
    )
    p.add_argument("--perception", metavar="FILE", help="perception settings (the rope's colour range)")
    p.add_argument(
        "--config", metavar="FILE", help="service config: gripper convention, world frame, camera pose"
    )
    p.add_argument(
        "--vertices",
        type=_count(5),
        metavar="N",
        help="vertices of the model (default: edges of at most about 9 cm, 12..14 vertices)",
    )
    p.add_argument(
        "--out", default="calibrated.pt", metavar="MODEL.pt", help="model file (default calibrated.pt)"
    )
    p.add_argument(
        "--report", metavar="DIR", help="report directory (default: MODEL_report beside the model)"
    )
    for name, what in (
        ("poses", "gripper poses (PoseArray)"),
        ("points", "clouds (PointCloud2)"),
        ("camera-info", "camera intrinsics (CameraInfo)"),
        ("camera-pose", "camera pose (PoseStamped or TFMessage)"),
    ):
        p.add_argument(
            f"--topic-{name}", metavar="TOPIC", help=f"the topic of the {what}; default: found by type"
        )
    b = p.add_argument_group("budget (defaults: 15-19 min for 50 s of clips on one core)")
    b.add_argument(
        "--iterations", type=_count(1), default=None, help="training iterations of the first round"
    )
    b.add_argument("--refine-iterations", type=_count(1), default=None, help="of each later round")
    b.add_argument("--rounds", type=_count(1), default=None, help="train-and-track-again rounds at most")
    b.add_argument("--horizon", type=_count(2), default=None, help="training window [steps]")
    b.add_argument("--batch", type=_count(1), default=None, help="training windows per iteration")
    b.add_argument(
        "--time-limit",
        type=_positive,
        default=20.0,
        metavar="MIN",
        help="skip the last rounds and stop training early rather than run longer than this "
        "(default 20; on a busy 2-core machine it may leave out the third round from 50 s of clips, "
        "the second from 2 minutes or more: more clips want more time)",
    )
    p.add_argument(
        "--prior-without",
        nargs="+",
        default=[],
        metavar="ROD",
        help="shipped rods (DLO1..DLO5) left out of the starting stiffness prior: when the rope "
        "calibrated is one of them, it then has no part in its own prior (the report lists the "
        "rods the prior comes from)",
    )
    p.add_argument("--threads", type=_count(1), default=1, help="torch threads (default 1)")
    p.add_argument(
        "--workers",
        type=_count(1),
        default=None,
        help="processes that track the clips and roll out the held-out fits side by side, one torch "
        "thread each (default: the cores this process may use; 1: none); the same model with any number",
    )
    p.add_argument("--seed", type=int, default=0)
    return p


def _settings(args):
    """(service config, perception config) from the files given; errors as one line."""
    from perception import load_config as load_perception
    from service.config import ServiceConfigError
    from service.config import load_config as load_service

    try:
        cfg = load_service(args.config)
    except ServiceConfigError as exc:
        raise CalibrationError(str(exc)) from None
    source = args.perception or cfg.perception
    try:
        perception = load_perception(source)
    except (OSError, ValueError, TypeError) as exc:
        raise CalibrationError(f"perception settings {source}: {exc}".replace("\n", " ")) from None
    if args.diameter:
        radius = args.diameter / 2
        perception = replace(
            perception,
            estimation=replace(perception.estimation, surface_offset=radius),
            tracker=replace(perception.tracker, rope_radius=radius),
        )
    return cfg, perception


def _prior(leave_out: list[str]) -> tuple[float, list[str]]:
    """``(the starting stiffness prior, the shipped rods it comes from)``, without ``leave_out``. A
    name that is not shipped here (a rod whose files were removed, as the acceptance removes the
    calibrated rope's) has no part in the prior anyway: the report lists the rods that do."""
    from deform import ConfigError, bend_per_linear_density
    from deform.config import prior_rods

    try:
        prior = bend_per_linear_density(leave_out)
    except ConfigError as exc:
        raise CalibrationError(f"--prior-without: {exc}") from None
    return prior, prior_rods(leave_out)


def run(args, age_s: float = 0.0) -> int:
    started = time.perf_counter() - age_s  # the time limit counts from the command's start
    import torch

    from calibrate import report
    from calibrate.bags import Topics, read_clip
    from calibrate.fit import Budget, calibrate
    from calibrate.latency import cloud_delay
    from deform.cores import available_cores

    torch.set_num_threads(args.threads)
    out = Path(args.out)
    if out.suffix != ".pt":
        raise CalibrationError(
            f"{out}: the model file must end in .pt (what deform.load_model reads as a file)"
        )
    report_dir = Path(args.report) if args.report else out.with_name(f"{out.stem}_report")
    cfg, perception = _settings(args)
    prior, prior_rods = _prior(args.prior_without)
    topics = Topics(args.topic_poses, args.topic_points, args.topic_camera_info, args.topic_camera_pose)
    clips = [read_clip(b, cfg, topics) for b in args.bags]
    names = [c.name for c in clips]
    if len(set(names)) < len(names):
        raise CalibrationError(f"two bags have the same name ({', '.join(names)}): rename one")
    delay = cloud_delay(clips, cfg.grippers, perception.segmentation)
    if delay.told:  # clouds stamped late (or early): tracked at the time they were taken
        clips = [replace(c, cloud_delay_ns=round(delay.delay_s * 1e9)) for c in clips]
    given = {
        k: v
        for k, v in {
            "iterations": args.iterations,
            "refine_iterations": args.refine_iterations,
            "rounds": args.rounds,
            "horizon": args.horizon,
            "batch": args.batch,
        }.items()
        if v is not None
    }
    spent = time.perf_counter() - started  # starting, reading the settings and the bags count too
    budget = replace(Budget(seed=args.seed, time_limit_s=60.0 * args.time_limit - spent), **given)
    if args.horizon is not None:
        budget = replace(budget, curriculum=tuple(h for h in budget.curriculum if h < args.horizon))
    workers = args.workers or available_cores()
    cal = calibrate(
        clips,
        args.length,
        args.mass,
        cfg.grippers,
        perception,
        n_vertices=args.vertices,
        budget=budget,
        name=out.stem,
        prior=prior,
        workers=workers,
    )
    inputs = {
        "bags": [str(b) for b in args.bags],
        "length_m": args.length,
        "mass_kg": args.mass,
        "diameter_m": args.diameter,
        "vertices": cal.start.cfg.n_vertices,  # --vertices, or the default for the length
        "stiffness_prior": {
            "without": list(args.prior_without),
            "from": prior_rods,
            "bend_per_linear_density": prior,
        },
        "perception": args.perception or cfg.perception,
        "config": args.config,
        "out": str(out),
        "budget": {k: v for k, v in vars(budget).items()},
        "cloud_delay": delay.as_dict(),
        "workers": workers,
    }
    if cal.model is None:
        report.write(cal, clips, inputs, report_dir)
        print(f"{PROG}: error: {cal.problem} (no model written; report in {report_dir})", file=sys.stderr)
        return 2
    cal.model.save(
        out, {"calibration": {"bags": inputs["bags"], "length_m": args.length, "mass_kg": args.mass}}
    )
    report.write(cal, clips, inputs, report_dir)
    last = [r for r in cal.rounds if r.kept][-1]
    print(
        json.dumps(
            {
                "model": str(out),
                "report": str(report_dir),
                "held_out_prediction_fit_m": last.held_out_fit_m,
                "rounds": len(cal.rounds) - 1,
                "seconds": round(cal.seconds, 1),
            }
        )
    )
    return 0


def main(argv: list[str] | None = None, age_s: float = 0.0) -> int:
    """The command.

    Args:
        argv: arguments (None: ``sys.argv``).
        age_s: how long ago the command started [s], counted in ``--time-limit``
            (``python -m calibrate``: :func:`command_age_s`; a call from Python: 0, from now).

    Returns:
        0, or 2 for bad input (one line on stderr) or clips that identify nothing.
    """
    args = build_parser().parse_args(argv)
    from deform import ConfigError

    try:
        return run(args, age_s)
    except (CalibrationError, ConfigError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
