"""The service's estimator on a simulated clock: clouds that arrive late, poses that arrive in bursts.

    .venv/bin/python benchmarks/service_timing.py [--latency-ms 0 50 100] [--ticks 2000] [--json out.json]

The wall-clock service's own code (``Estimator`` and ``FusionWorker`` with the inline worker, the
default config otherwise) driven tick by tick on a simulated clock, so that every mode sees exactly
the same inputs and the figures do not move with the machine's load (``service_latency.py`` runs the
live service; its runs vary by 2x from one service start to the next, see docs/service.md). The
recording is played back and forth at 100 Hz; poses are stamped on schedule and reach the loop in
bursts (per tick 0, 1 or 2 of them, the loop's clock drifting against the robot's by 0.5 %); each
cloud (30 Hz) is fused ``latency`` plus 20-40 ms (transport, decoding) after its stamp. Modes: the
service before (clouds fused where they arrive, each tick to the newest pose), the default (clouds
fused at their stamp), and that with the poses sampled one period a tick by their stamps
(``pose_delay_s`` 15 ms, off by default). Error: the
tracking error (two-way distance to the rope as rendered) of the estimate after each tick against the
recording at the time of the poses it stepped to, mean and p90 after the first 3 s.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

MODES = {
    "arrival, newest pose": {"camera": {"fuse_at": "arrival"}, "pose_delay_s": 0.0},
    "stamp, newest pose": {"camera": {"fuse_at": "stamp"}, "pose_delay_s": 0.0},  # the default
    "stamp, steady poses": {"camera": {"fuse_at": "stamp"}, "pose_delay_s": 0.015},  # 1.5 pose intervals
}
N_FRAMES = 500
DT_NS = 10_000_000
T0 = 1_700_000_000 * 10**9
SETTLE_TICKS = 300
DRIFT = 0.005  # the loop's clock runs this much fast against the robot's


def run(mode: dict, latency_s: float, ticks: int, seed: int = 0) -> dict:
    import torch

    from benchmarks.service_bench import frame_at
    from benchmarks.tracking.metric import rope_error
    from deform import load_model
    from service import messages as M
    from service import scenario
    from service.config import load_config
    from service.estimator import Estimator
    from service.fusion import FusionWorker
    from service.geometry import matrix_to_pose, poses_from_vertices

    torch.set_num_threads(1)
    positions, _ = scenario.demo_positions(N_FRAMES)
    grippers = scenario.offsets_for(positions)
    poses = poses_from_vertices(positions, grippers)
    frames = {f.step: f for f in scenario.render(positions, 0.01, 30.0)}
    cfg = load_config(None, compile_step=False, grippers=grippers.model_dump(), **mode)
    est = Estimator(cfg, load_model(cfg.rod))
    fusion = FusionWorker(est)
    cam = next(iter(frames.values())).camera
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    est.on_camera_info(M.camera_info(T0, K, cam.width, cam.height))
    est.on_camera_pose(M.pose_stamped(T0, matrix_to_pose(cam.world_from_camera)))
    rng = np.random.default_rng(seed)
    sent, clouds, errors = 0, [], []
    frame_of = {}  # pose stamp -> frame
    for tick in range(ticks):
        now = T0 + round(tick * DT_NS * (1 + DRIFT))
        # the poses due by now, sent in a burst of at most two (a busy sender catches up)
        burst = int(rng.choice([0, 1, 2], p=[0.2, 0.6, 0.2]))
        for _ in range(burst):
            stamp = T0 + sent * DT_NS
            if stamp > now:
                break
            i = frame_at(sent, N_FRAMES)
            frame_of[stamp] = i
            assert est.on_poses(M.pose_array(stamp, poses[i]))
            if i in frames:
                ready = stamp + round((latency_s + rng.uniform(0.02, 0.04)) * 1e9)
                clouds.append((ready, M.point_cloud(stamp, frames[i].xyz, frames[i].rgb)))
            sent += 1
        if est.poses is None:
            continue
        est.tick(now)
        while clouds and clouds[0][0] <= now:
            fusion.fuse(est.decode_cloud(clouds.pop(0)[1]))
        if tick >= SETTLE_TICKS:
            # the time the state was stepped to (a sample past the newest pose holds that pose)
            t = min(est.history[-1].pose_ns, T0 + (sent - 1) * DT_NS)
            k = (t - T0) // DT_NS
            a = (t - T0 - k * DT_NS) / DT_NS
            f0 = frame_of[T0 + k * DT_NS]
            f1 = frame_of.get(T0 + (k + 1) * DT_NS, f0)
            truth = (1 - a) * positions[f0] + a * positions[f1]
            errors.append(rope_error(est.tracker.x, truth))
    e = 1e3 * np.array(errors)
    return {
        "error_mm": round(float(e.mean()), 2),
        "error_p90_mm": round(float(np.percentile(e, 90)), 2),
        "rope": est.rope_status(),
        "clouds_fused": est.stats.snapshot()["counts"].get("clouds_fused", 0),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--latency-ms", type=float, nargs="+", default=[0.0, 50.0, 100.0])
    ap.add_argument("--ticks", type=int, default=2000)
    ap.add_argument("--json")
    args = ap.parse_args()
    from benchmarks.provenance import provenance
    from service import scenario

    out: dict = {**provenance(), "recording": scenario.demo_positions(N_FRAMES)[1], "ticks": args.ticks}
    out["modes"] = {}
    for name, mode in MODES.items():
        out["modes"][name] = {}
        for ms in args.latency_ms:
            row = run(mode, ms / 1e3, args.ticks)
            out["modes"][name][f"{ms:g}"] = row
            print(name, ms, json.dumps(row), flush=True)
    now, before = out["modes"]["stamp, newest pose"], out["modes"]["arrival, newest pose"]
    out["ratio_default_over_before"] = {k: round(now[k]["error_mm"] / before[k]["error_mm"], 3) for k in now}
    print(json.dumps(out["ratio_default_over_before"]))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
