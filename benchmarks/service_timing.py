"""The service's estimator on a simulated clock: clouds that arrive late, poses that arrive in bursts.

    .venv/bin/python benchmarks/service_timing.py [--latency-ms 0 50 100] [--ticks 2000] [--json out.json]

The wall-clock service's own code (``Estimator`` and ``FusionWorker`` with the inline worker, the
default config otherwise) driven tick by tick on a simulated clock, so that every mode sees exactly
the same inputs and the figures do not move with the machine's load (``service_latency.py`` runs the
live service, start after start, and moves with the machine's load). The
recording is played back and forth at 100 Hz; poses are stamped on schedule and reach the loop in
bursts (on a fifth of the ticks the sender is busy and what was due comes with the next; the loop's
clock drifts against the robot's by 0.5 %; its first tick, which settles the rope, takes half a
second, the ticks meanwhile skipped as the live loop skips them); the
camera takes clouds at 30 Hz on its own clock (a random phase against the poses; each rendered from
the rope at its time), and each is decoded ``latency`` plus 5-30 ms (transport, decoding) after its
stamp and fused once due (``FusionWorker.due``: a cloud newer than every tick waits for its own, as
the service's fusion thread waits). Modes: the
service before (clouds fused where they arrive, each tick to the newest pose), clouds fused at their
stamp alone, and the defaults (also the poses sampled one period a tick by their stamps,
``pose_delay_s``). Error: the
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
    "stamp, newest pose": {"camera": {"fuse_at": "stamp"}, "pose_delay_s": 0.0},
    "stamp, steady poses": {},  # the defaults (pose_delay_s: 1.5 pose intervals)
}
N_FRAMES = 500
DT_NS = 10_000_000
T0 = 1_700_000_000 * 10**9
SETTLE_TICKS = 300
NS = 10**9
CAMERA_HZ = 30.0
DRIFT = 0.005  # the loop's clock runs this much fast against the robot's
BUSY = 0.2  # the pose sender's share of ticks too busy to send (what was due then comes in a burst)
INIT_S = 0.5  # the first tick's static solve (Tracker.initialize settles the rope: 0.48-0.50 s on one
# core, measured): the live loop skips the ticks meanwhile, while poses and clouds keep coming
TRANSPORT_S = (0.005, 0.03)  # a cloud's transport and decoding after the camera's latency: loopback (the
# live service measured 8 ms from stamp to decoded) to a network


def played(positions: np.ndarray, t_ns: int) -> np.ndarray:
    """The rope at time ``t_ns`` of the playback (frame ``frame_at(k)`` at ``T0 + k dt``, linear between)."""
    from benchmarks.service_bench import frame_at

    k, r = divmod(t_ns - T0, DT_NS)
    a = r / DT_NS
    return (1 - a) * positions[frame_at(k, N_FRAMES)] + a * positions[frame_at(k + 1, N_FRAMES)]


_CLOUDS: dict = {}


def clouds(positions: np.ndarray, ticks: int, seed: int = 0) -> list[tuple[int, object]]:
    """The camera's clouds over ``ticks`` periods: taken at 30 Hz from a random phase (a camera runs on
    its own clock, unrelated to the robot's poses), each rendered from the rope at its time, stamped
    with it. Rendered once for every mode."""
    key = (ticks, seed)
    if key not in _CLOUDS:
        from perception import default_camera, load_config, render_recording

        rng = np.random.default_rng(seed + 1)
        offset = int(rng.integers(0, DT_NS))
        stamps = [T0 + offset + round(c * NS / CAMERA_HZ) for c in range(int(ticks * 0.01 * CAMERA_HZ))]
        shapes = np.stack([played(positions, t) for t in stamps])
        cfg = load_config(None).render
        frames = render_recording(
            shapes,
            dt=1 / CAMERA_HZ,
            steps=range(len(stamps)),
            camera=default_camera(positions, cfg),
            seed=seed,
        )
        _CLOUDS[key] = list(zip(stamps, frames, strict=True))
    return _CLOUDS[key]


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
    camera_clouds = clouds(positions, ticks, seed)
    cfg = load_config(None, compile_step=False, grippers=grippers.model_dump(), **mode)
    est = Estimator(cfg, load_model(cfg.rod))
    fusion = FusionWorker(est)
    cam = camera_clouds[0][1].camera
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    est.on_camera_info(M.camera_info(T0, K, cam.width, cam.height))
    est.on_camera_pose(M.pose_stamped(T0, matrix_to_pose(cam.world_from_camera)))
    rng = np.random.default_rng(seed)
    ready = [  # (decoded at, cloud): the camera's latency plus 5-30 ms of transport and decoding
        (stamp + round((latency_s + rng.uniform(TRANSPORT_S[0], TRANSPORT_S[1])) * NS), stamp, frame)
        for stamp, frame in camera_clouds
    ]
    waiting: list = []  # (decoded at, cloud) not yet due: newer than the newest tick (FusionWorker.due)
    sent, errors, busy_until = 0, [], 0
    for tick in range(ticks):
        now = T0 + round(tick * DT_NS * (1 + DRIFT))
        # the poses due by now, unless the sender is busy this tick (then they come with the next)
        busy = rng.random() < BUSY
        while not busy and T0 + sent * DT_NS <= now:
            assert est.on_poses(M.pose_array(T0 + sent * DT_NS, poses[frame_at(sent, N_FRAMES)]))
            sent += 1
        if est.poses is None or now < busy_until:
            continue
        first = not est.initialized
        est.tick(now)
        if first:
            busy_until = now + round(INIT_S * NS)
        while ready and ready[0][0] <= now:
            at, stamp, f = ready.pop(0)
            waiting.append((at, est.decode_cloud(M.point_cloud(stamp, f.xyz, f.rgb))))
        # as the fusion thread: a cloud waits for its tick, at most ahead_wait_s()
        while waiting and (fusion.due(waiting[0][1]) or now - waiting[0][0] >= fusion.ahead_wait_s() * NS):
            fusion.fuse(waiting.pop(0)[1])
        if tick >= SETTLE_TICKS:
            # the time the state was stepped to (a sample past the newest pose holds that pose)
            t = min(est.history[-1].pose_ns, T0 + (sent - 1) * DT_NS)
            errors.append(rope_error(est.tracker.x, played(positions, t)))
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
    finish(out, args.json)
    return 0


def finish(out: dict, json_path: str | None) -> None:
    """The defaults' error over the service before's per latency (means), printed; ``out`` written."""
    now, before = out["modes"].get("stamp, steady poses"), out["modes"].get("arrival, newest pose")
    if now and before:
        out["ratio_default_over_before"] = {
            k: round(now[k]["error_mm"] / before[k]["error_mm"], 3) for k in now
        }
        print(json.dumps(out["ratio_default_over_before"]))
    if json_path:
        Path(json_path).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
