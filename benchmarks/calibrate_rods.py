"""`deform calibrate` on DLO1..DLO5 (issue 49): a model from rendered camera clips alone, scored on
held-out motions beside the shipped motion-capture model and the generic DER of the same length and
mass, in one run.

    python benchmarks/calibrate_rods.py [--rods DLO1 ...] [--seconds 50 120 300] [--tracked 4] [--vertices N]
        [--quick] [--rescore-from CODE] [--num-cpus N | --address ray://HOST:PORT | --inline]

Per rod and amount of clips (a Ray task each, benchmarks/cluster.py): the clips are cut from the
rod's training motions (benchmarks/calibration/clips.py: one camera for the session, noise,
dropouts, an occluder in every other clip), written as MCAP bags, and `deform calibrate BAGS
--length L --mass M --config service.yaml` runs on them with its defaults, timed. The calibrated,
shipped and generic models are scored on the held-out motions (eval, or the held-out fifth of
train for DLO4 and DLO5; benchmarks/calibration/score.py): the paper's 500-step open loop, tracking
through occlusion, the 1 s prediction from the tracked state. The calibration never reads a model
file: it knows the rope by the clips, its length and its mass. As in the issue's acceptance, it runs
without the rope's shipped files: its processes cannot open them (benchmarks/calibration/unreadable.py).

``--rescore-from CODE`` scores the models a stored run (of that code digest) calibrated again, without
calibrating: for a change of the scoring alone (the rows keep that run's calibration times).

Results are stored per rod and amount as they finish (``benchmarks/results/calibrate_rods.runs/``;
a rerun resumes), with the calibrated model and its report in ``runs/calibrate_rods/``. Summary:
``benchmarks/results/calibrate_rods.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from functools import partial
from pathlib import Path

if not __package__:  # run as `python benchmarks/calibrate_rods.py`: import the repository's packages
    sys.path[0] = str(Path(__file__).resolve().parents[1])

from benchmarks.calibration.foreign_session import (
    FOREIGN_LABS,
    film_foreign,
    foreign_camera,
    foreign_perception,
    write_foreign_session,
)
from benchmarks.calibration.report import markdown, summarize
from benchmarks.calibration.setups import SETUPS
from benchmarks.calibration.unreadable import shipped_files, withheld
from benchmarks.cluster import Workers, add_arguments, call, repo_path
from benchmarks.provenance import provenance
from benchmarks.store import RunStore, source_digest, write_result

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
RODS = ("DLO1", "DLO2", "DLO3", "DLO4", "DLO5")
QUICK_BUDGET = [
    "--iterations",
    "3",
    "--refine-iterations",
    "2",
    "--rounds",
    "1",
    "--horizon",
    "20",
    "--batch",
    "2",
]
QUICK_FRAMES = 250  # 2.5 s clips and held-out motions in --quick


def calibrate_rod(
    rod: str,
    seconds: float,
    tracked: int,
    quick: bool,
    runs: str,
    vertices: int | None = None,
    setup: str = "session",
    clip_set: int = 0,
    workers: int | None = None,
) -> dict:
    """A task: clips of ``seconds`` of the rod's training motions (``clip_set``:
    benchmarks.calibration.clips.motions) filmed as the lab ``setup`` films
    (benchmarks/calibration/setups.py), `deform calibrate` on them (its default vertex count, or
    ``vertices``; ``workers``: its ``--workers``, else its default), and the three models scored on the
    held-out motions, filmed the same way."""
    import torch

    from benchmarks.calibration.clips import write_session
    from benchmarks.calibration.score import score
    from deform import DeformModel

    clips, held, lab, camera = _session(rod, seconds, quick, setup, clip_set)
    perception = _perception(setup, lab)
    name = (
        f"{rod}-{int(seconds)}s"
        + (f"-{vertices}v" if vertices else "")
        + (f"-{setup}" if setup != "session" else "")
        + (f"-set{clip_set}" if clip_set else "")
        + (f"-{workers}w" if workers else "")
    )
    out = repo_path(runs) / name
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f"calibrate_{rod}_"))
    try:
        t0 = time.perf_counter()
        if setup in FOREIGN_LABS:
            session = write_foreign_session(rod, clips, work, lab, camera)
        else:
            session = write_session(rod, clips, work, lab, camera)
        shutil.copy(session.config, out / "service.yaml")  # the gripper convention, to score with
        render_s = time.perf_counter() - t0
        model_path = out / "calibrated.pt"
        cmd = [
            sys.executable, "-m", "calibrate", *map(str, session.bags),
            "--length", f"{session.length_m}", "--mass", f"{session.mass_kg}",
            "--config", str(session.config), "--out", str(model_path), "--report", str(out / "report"),
            "--prior-without", rod,  # the rope under test has no part in its own prior
            *(["--perception", str(session.perception)] if session.perception else []),
            *(QUICK_BUDGET if quick else []),
            *(["--vertices", str(vertices)] if vertices else []),
            *(["--workers", str(workers)] if workers else []),
        ]  # fmt: skip
        with withheld(shipped_files(rod)) as env:  # as the acceptance: the rope's shipped files removed
            t0 = time.perf_counter()
            done = subprocess.run(cmd, cwd=repo_path("."), capture_output=True, text=True, env=env)
            calibrate_s = time.perf_counter() - t0
    finally:
        shutil.rmtree(work, ignore_errors=True)  # the bags: about 200 MB a clip
    if done.returncode != 0:
        raise RuntimeError(f"deform calibrate on {rod} exited with {done.returncode}: {done.stderr[-2000:]}")
    printed = json.loads(done.stdout.strip().splitlines()[-1])
    report = json.loads((out / "report" / "report.json").read_text())
    torch.set_num_threads(1)
    calibrated = DeformModel.load(model_path)
    cfg = calibrated.cfg
    with _film(setup, lab, camera, out / "service.yaml", _stamp_delay_s(report)) as film:
        scores = score(
            _three_models(calibrated, rod, session.length_m, session.mass_kg),
            held,
            tracked,
            camera,
            perception,
            fps=lab.fps,
            film=film,
        )
    return dict(
        rod=rod,
        seconds=session.seconds,
        clips=[c.name for c in clips],
        held_out=[h.name for h in held],
        render_s=round(render_s, 1),
        calibrate_s=round(calibrate_s, 1),
        calibrate_printed=printed,
        withheld_from_calibration=shipped_files(rod),
        identified=report.get("identified"),
        cloud_delay=report["inputs"].get("cloud_delay"),
        rounds=report.get("rounds"),
        vertices=cfg.n_vertices,
        scores=scores,
        model=str(
            model_path.relative_to(repo_path("."))
            if model_path.is_relative_to(repo_path("."))
            else model_path
        ),
    )


def _session(rod: str, seconds: float, quick: bool, setup: str = "session", clip_set: int = 0) -> tuple:
    """``(clips, held_out, setup, camera)``: the rod's clip and held-out motions (2.5 s of two clips
    and one held-out motion in ``quick``), the lab's :class:`Setup` and the one camera that films the
    session."""
    from dataclasses import replace as dc_replace

    from benchmarks.calibration.clips import motions
    from benchmarks.calibration.setups import SETUPS, session_camera

    clips, held = motions(rod, seconds, clip_set=clip_set)
    if quick:
        clips = [dc_replace(c, positions=c.positions[:QUICK_FRAMES]) for c in clips[:2]]
        held = [dc_replace(h, positions=h.positions[:QUICK_FRAMES]) for h in held[:1]]
    positions = [r.positions for r in clips + held]
    if setup in FOREIGN_LABS:
        lab = FOREIGN_LABS[setup]
        return clips, held, lab, foreign_camera(lab, positions)
    lab = SETUPS[setup]
    return clips, held, lab, session_camera(lab, positions)


def _perception(setup: str, lab):
    """The perception settings a lab's user passes: its colour range over perception's defaults."""
    return foreign_perception(lab) if setup in FOREIGN_LABS else lab.perception()


def _stamp_delay_s(report: dict) -> float:
    """The clouds' stamp delay a calibration's ``report.json`` tells the service to take out
    (``camera.stamp_delay_s``; 0 for a report from before it estimated one)."""
    return float(report["inputs"].get("cloud_delay", {}).get("delay_s", 0.0))


@contextmanager
def _film(setup: str, lab, camera, config: Path, stamp_delay_s: float = 0.0):
    """How the held-out motions are filmed: None (perception's renderer with the setup's camera) or,
    for the foreign lab, its bags read back by `deform calibrate`'s reader (in a scratch directory),
    their clouds dated as a service configured with the report's ``stamp_delay_s`` dates them."""
    if setup not in FOREIGN_LABS:
        yield None
        return
    work = Path(tempfile.mkdtemp(prefix="calibrate_held_"))
    try:
        yield partial(
            film_foreign,
            lab=lab,
            world_from_optical=camera,
            work=work,
            config=config,
            stamp_delay_s=stamp_delay_s,
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _three_models(calibrated, rod: str, length_m: float, mass_kg: float) -> dict:
    """The calibrated model, the shipped mocap-trained one and the generic DER of the same length and
    mass (its prior without ``rod``)."""
    from deform import bend_per_linear_density, generic_model, load_model

    return {
        "calibrated": calibrated,
        "shipped": load_model(rod),
        "generic": generic_model(length_m, mass_kg, prior=bend_per_linear_density([rod])),
    }


def rescore_rod(rod: str, seconds: float, tracked: int, old: dict) -> dict:
    """A task: the model a stored run calibrated (``old``: its row, its model file) scored again by
    today's scoring on the same held-out motions and camera, without calibrating again; the row
    keeps that run's calibration (time, rounds) and names the code that calibrated (``rescored_from``:
    that run's, or the one it named when it was itself a rescoring)."""
    import torch

    from benchmarks.calibration.clips import held_length_and_mass
    from benchmarks.calibration.score import score
    from deform import DeformModel

    setup = old.get("config", {}).get("setup", "session")
    clip_set = old.get("config", {}).get("clip_set", 0)
    clips, held, lab, camera = _session(rod, seconds, quick=False, setup=setup, clip_set=clip_set)
    length_m, mass_kg = held_length_and_mass(rod, clips)
    torch.set_num_threads(1)
    calibrated = DeformModel.load(repo_path(old["model"]))
    models = _three_models(calibrated, rod, length_m, mass_kg)
    run_dir = repo_path(old["model"]).parent
    delay = _stamp_delay_s(json.loads((run_dir / "report" / "report.json").read_text()))
    with _film(setup, lab, camera, run_dir / "service.yaml", delay) as film:
        scores = score(models, held, tracked, camera, _perception(setup, lab), fps=lab.fps, film=film)
    kept = {k: v for k, v in old.items() if k not in ("key", "config", "scores")}
    return {**kept, "scores": scores, "rescored_from": old.get("rescored_from") or old["config"]["code"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rods", nargs="*", default=list(RODS))
    ap.add_argument("--seconds", nargs="*", type=float, default=[50.0], help="clip time per calibration")
    ap.add_argument(
        "--tracked", type=int, default=4, help="held-out motions tracked per rod (all: open loop)"
    )
    ap.add_argument("--quick", action="store_true", help="two 2.5 s clips, a tiny budget (a smoke test)")
    ap.add_argument(
        "--vertices", type=int, default=None, help="the calibrated model's vertex count (default: the tool's)"
    )
    ap.add_argument(
        "--runs",
        default="runs/calibrate_rods",
        help="models and reports (a relative path is inside the repository)",
    )
    ap.add_argument(
        "--rescore-from",
        metavar="CODE",
        help="score the models of the stored run of this code digest again (their model files in --runs), "
        "without calibrating: a change of the scoring only",
    )
    ap.add_argument(
        "--setup",
        default="session",
        choices=[*sorted(SETUPS), *FOREIGN_LABS],
        help="how the lab films: camera, rate, rope colour, noise (benchmarks/calibration/setups.py); "
        "'foreign': a lab whose renderer and bag writer share no code with ours "
        "(benchmarks/calibration/foreign_lab.py)",
    )
    ap.add_argument(
        "--clip-set",
        type=int,
        default=0,
        help="another set of training motions of the same size and spread (0: the usual one; k: each "
        "clip the k-th recording after it): how much a calibration depends on the motions filmed",
    )
    ap.add_argument(
        "--calibrate-workers",
        type=int,
        default=None,
        metavar="N",
        help="deform calibrate --workers N (default: its own default, the cores available): one worker "
        "beside the default in one run shows what the workers gain",
    )
    ap.add_argument("--stem", default="calibrate_rods", help="results benchmarks/results/<stem>.{json,md}")
    ap.add_argument("--out", type=Path, default=RESULTS)
    add_arguments(ap)
    args = ap.parse_args(argv)
    code = source_digest(  # the code a row's numbers depend on (not the summary's)
        "deform",
        "perception",
        "calibrate",
        "service",
        "benchmarks/calibration/clips.py",
        "benchmarks/calibration/score.py",
        # the shipped models, scored beside the calibrated ones (a retrained one: --rescore-from)
        *(f"deform/models/{rod}.pt" for rod in RODS),
        *(
            ["benchmarks/calibration/foreign_lab.py", "benchmarks/calibration/foreign_session.py"]
            if args.setup in FOREIGN_LABS
            else []
        ),
    )
    config = dict(tracked=args.tracked, quick=args.quick, code=code)
    if args.vertices:
        config["vertices"] = args.vertices
    if args.setup != "session":  # rows of the default lab keep their keys
        config["setup"] = args.setup
    if args.clip_set:  # ... and of the usual clips
        config["clip_set"] = args.clip_set
    if args.calibrate_workers:  # ... and of deform calibrate's default workers
        config["calibrate_workers"] = args.calibrate_workers
    store = RunStore(args.out / f"{args.stem}.runs")
    done = store.load(config)
    keys = {f"{rod}-{int(s)}s": (rod, s) for s in args.seconds for rod in args.rods}
    if args.rescore_from:
        old = store.load(dict(config, code=args.rescore_from))
        missing = [k for k in keys if k not in done and k not in old]
        if missing:
            ap.error(f"no stored row of code {args.rescore_from} for {', '.join(missing)}")
        tasks = {
            key: call(rescore_rod, rod, s, args.tracked, old[key])
            for key, (rod, s) in keys.items()
            if key not in done
        }
    else:
        tasks = {
            key: call(
                calibrate_rod,
                rod,
                s,
                args.tracked,
                args.quick,
                args.runs,
                args.vertices,
                args.setup,
                args.clip_set,
                args.calibrate_workers,
            )
            for key, (rod, s) in keys.items()
            if key not in done
        }

    def stored(key: str, value: dict) -> None:
        row = {"key": key, "config": config, **value}
        store.save(row)
        done[key] = row
        s = value["scores"]
        workers.log(
            f"{key}: open loop {s['calibrated']['open_loop']['l1_cm']} cm "
            f"(shipped {s['shipped']['open_loop']['l1_cm']}, generic {s['generic']['open_loop']['l1_cm']}); "
            f"calibrate {value['calibrate_s']:.0f} s"
        )

    t0 = time.time()
    with Workers.from_args(args) as workers:
        failures = workers.run(tasks, stored, desc=args.stem)
    rows = [done[k] for k in keys if k in done]
    result = {
        **provenance(argv, script="benchmarks/calibrate_rods.py", threads=1),
        "workers": workers.describe(),
        "args": dict(
            rods=args.rods,
            seconds=args.seconds,
            tracked=args.tracked,
            quick=args.quick,
            vertices=args.vertices,
            setup=args.setup,
            clip_set=args.clip_set,
        ),
        "wall_s": round(time.time() - t0, 1),
        "complete": not failures,
        "summary": summarize(rows),
        "rows": rows,
    }
    print(markdown(result))
    return write_result(args.out / args.stem, result, failures, "calibration(s)", markdown(result))


if __name__ == "__main__":
    raise SystemExit(main())
