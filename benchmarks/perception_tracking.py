"""Benchmark of the perception tracker on rendered clouds of the real DEFORM eval recordings.

For each recording: clouds rendered at 30 fps with 0, 25 and 50 % of the rope hidden (from 30 % to 80 %
of the recording); L1 error over 5 s (paper's metric: mean |prediction - truth| over steps, vertices
and xyz, from frames 0 and 1) for camera updates at 0 (open loop), 1, 5, 10 and 30 fps, for the
DEFORM-model tracker and the non-physical baseline (vertices stay where last seen). Also the latency
of ``Tracker.correct`` (p50/p99), on the benchmark's clouds and on full-resolution (640x576) clouds.

    python benchmarks/perception_tracking.py            # 2 eval recordings per rod (DLO1..DLO3)
    python benchmarks/perception_tracking.py --quick    # 1 recording per rod
    python benchmarks/perception_tracking.py --per-rod 0  # every eval recording (slow: ~30 min)
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core, as the latency budget says
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import sys
import time
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from deform import find_data_root, generate_recording, gripped_indices, load_model, load_recording
from perception import Tracker, camera_steps, load_config, render_recording

RATES = (0, 1, 5, 10, 30)
OCCLUSIONS = (0.0, 0.25, 0.5)
OUT = Path(__file__).resolve().parent / "results"


def run(model, positions, frames, physics, config, latencies=None):
    """L1 error (m) of one tracker over the recording, corrected at the steps of ``frames``."""
    gi = gripped_indices(model.n)
    tracker = Tracker(model, config=config, physics=physics)
    tracker.initialize_from_frames(positions[0], positions[1])
    by_step = {f.step: f for f in frames}
    err = []
    for k in range(2, len(positions)):
        x, _ = tracker.step(positions[k, gi])
        f = by_step.get(k)
        if f is not None:
            t0 = time.perf_counter()
            x, _ = tracker.correct(f.xyz, f.rgb, f.camera)
            if latencies is not None:
                latencies.append(time.perf_counter() - t0)
        err.append(np.abs(x - positions[k]).mean())
    return float(np.mean(err))


def recordings(per_rod: int, rods):
    root = find_data_root()
    if root is None:
        print("real data not found: using synthetic recordings")
        for rod in rods:
            model = load_model(rod)
            for seed in range(max(per_rod, 1)):
                yield (
                    rod,
                    f"synthetic_{seed}",
                    generate_recording(model, n_frames=500, seed=2 * seed).positions,
                )
        return
    for rod in rods:
        files = sorted(
            (root / rod / "eval").glob("*.pkl"), key=lambda p: int(p.stem) if p.stem.isdigit() else p.stem
        )
        for path in files[: per_rod or None]:
            yield rod, path.stem, load_recording(path).positions


def full_resolution_latency(model, positions, config, n_frames: int = 60):
    cfg = replace(config, render=replace(config.render, scale=1.0, occlusion=0.25))
    steps = camera_steps(len(positions), model.dt, 30)[1 : n_frames + 1]
    frames = render_recording(positions, dt=model.dt, config=cfg, steps=steps, seed=0)
    tracker = Tracker(model, config=config)
    tracker.initialize_from_frames(positions[steps[0] - 2], positions[steps[0] - 1])
    gi = gripped_indices(model.n)
    lat, k = [], steps[0] - 1
    for f in frames:
        while k < f.step:
            k += 1
            tracker.step(positions[k, gi])
        t0 = time.perf_counter()
        tracker.correct(f.xyz, f.rgb, f.camera)
        lat.append(time.perf_counter() - t0)
    return lat, frames[0].xyz.shape[:2]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="one recording per rod")
    ap.add_argument("--per-rod", type=int, default=2, help="eval recordings per rod (0 = all)")
    ap.add_argument("--rods", nargs="+", default=["DLO1", "DLO2", "DLO3"])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument(
        "--perception",
        type=Path,
        default=None,
        help="the tracker's settings (YAML; default: the shipped ones)",
    )
    args = ap.parse_args(argv)
    per_rod = 1 if args.quick else args.per_rod
    torch.set_num_threads(1)
    base = load_config(args.perception)
    rows, latencies, hidden = [], [], {}
    t_start = time.time()
    models = {}
    for rod, name, positions in recordings(per_rod, args.rods):
        model = models.setdefault(rod, load_model(rod))
        n = positions.shape[1]
        with torch.no_grad():
            open_loop = run(model, positions, [], True, base)
            hold = run(model, positions, [], False, base)
        for occ in OCCLUSIONS:
            cfg = replace(base, render=replace(base.render, occlusion=occ))
            frames = render_recording(
                positions,
                dt=model.dt,
                fps=30,
                config=cfg,
                seed=zlib.crc32(f"{rod}/{name}".encode()) % 1000,  # hash() differs per process
            )
            frames = [f for f in frames if f.step >= 2]
            during = [1 - f.visible[2 : n - 2].mean() for f in frames if f.occluded]
            if during:
                hidden.setdefault(occ, []).extend(during)
            for fps in RATES:
                sub = set(camera_steps(len(positions), model.dt, fps))
                fr = [f for f in frames if f.step in sub]
                for tracker, physics in (("deform", True), ("baseline", False)):
                    if fps == 0:
                        err = open_loop if physics else hold
                    else:
                        err = run(
                            model, positions, fr, physics, cfg, latencies if (physics and fps == 30) else None
                        )
                    rows.append(
                        dict(
                            rod=rod, recording=name, occlusion=occ, fps=fps, tracker=tracker, l1_cm=100 * err
                        )
                    )
            print(
                f"{rod} {name} occlusion {occ:.2f}: "
                + ", ".join(
                    f"{r['tracker'][0]}{r['fps']}={r['l1_cm']:.2f}"
                    for r in rows
                    if r["recording"] == name and r["rod"] == rod and r["occlusion"] == occ
                ),
                flush=True,
            )
    first = next(recordings(1, args.rods[:1]))[2]
    lat_full, shape_full = full_resolution_latency(models[args.rods[0]], first, base)
    summary = {}
    for r in rows:
        summary.setdefault((r["occlusion"], r["tracker"], r["fps"]), []).append(r["l1_cm"])
    from benchmarks.provenance import provenance

    result = dict(
        **provenance(argv, script="benchmarks/perception_tracking.py"),
        args=dict(
            per_rod=per_rod,
            rods=args.rods,
            perception=None if args.perception is None else str(args.perception),
        ),
        wall_s=round(time.time() - t_start, 1),
        hidden_fraction_of_free_vertices=dict((str(k), float(np.mean(v))) for k, v in hidden.items()),
        mean_l1_cm=[
            dict(occlusion=k[0], tracker=k[1], fps=k[2], l1_cm=float(np.mean(v)), n=len(v))
            for k, v in sorted(summary.items())
        ],
        latency_ms=dict(
            bench_resolution=dict(
                p50=1e3 * float(np.percentile(latencies, 50)),
                p99=1e3 * float(np.percentile(latencies, 99)),
                n=len(latencies),
            ),
            full_resolution=dict(
                shape=list(shape_full),
                p50=1e3 * float(np.percentile(lat_full, 50)),
                p99=1e3 * float(np.percentile(lat_full, 99)),
                n=len(lat_full),
            ),
        ),
        rows=rows,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "perception.json").write_text(json.dumps(result, indent=1))
    (args.out / "perception.md").write_text(markdown(result))
    print(markdown(result))


def markdown(res) -> str:
    lines = [
        f"L1 error [cm] over 5 s, mean of {len({(r['rod'], r['recording']) for r in res['rows']})} recordings "
        f"({', '.join(res['args']['rods'])}; {res['args']['per_rod'] or 'all'} per rod). "
        "Columns: camera updates per second (0 = open loop).",
        "",
        "| occlusion | tracker | " + " | ".join(f"{f} fps" for f in RATES) + " |",
        "|---|---|" + "---:|" * len(RATES),
    ]
    table = {(r["occlusion"], r["tracker"], r["fps"]): r["l1_cm"] for r in res["mean_l1_cm"]}
    for occ in OCCLUSIONS:
        for tr in ("deform", "baseline"):
            lines.append(
                f"| {int(occ * 100)} % | {tr} | "
                + " | ".join(f"{table[(occ, tr, f)]:.2f}" for f in RATES)
                + " |"
            )
    lat = res["latency_ms"]
    hid = res["hidden_fraction_of_free_vertices"]
    lines += [
        "",
        "Free vertices actually hidden while the occluder is present: "
        + ", ".join(
            f"{int(float(k) * 100)} % target: {100 * v:.0f} %" for k, v in hid.items() if float(k) > 0
        )
        + ".",
        "",
        f"`Tracker.correct` latency: {lat['bench_resolution']['p50']:.1f} ms p50, "
        f"{lat['bench_resolution']['p99']:.1f} ms p99 on 320x288 clouds ({lat['bench_resolution']['n']} updates); "
        f"{lat['full_resolution']['p50']:.1f} ms p50, {lat['full_resolution']['p99']:.1f} ms p99 on "
        f"{lat['full_resolution']['shape'][1]}x{lat['full_resolution']['shape'][0]} clouds "
        f"({lat['full_resolution']['n']} updates). One thread, {res['machine']['cpus']} CPUs, "
        f"wall time {res['wall_s']} s.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
