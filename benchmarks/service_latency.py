"""The live service's tracking error when clouds arrive late: the defaults (clouds fused at the tick of
their stamp, ``camera.fuse_at: stamp``; poses sampled one period a tick by their stamps,
``pose_delay_s``) against the service before (fused where they arrive, the newest pose) and the
first change alone, in one run. Each mode's service is started ``--repeats`` times: before the
first tick's poses were stepped through (docs/service.md) some starts fell into episodes of
repeated redetections and tracked up to 2x worse, so one start does not speak for the service.
``benchmarks/service_timing.py`` (a simulated clock, the same inputs for every mode) is the
comparison of record between modes; this is the check on the live system.

    .venv/bin/python benchmarks/service_latency.py [--latency-ms 0 50 100] [--run-s 20] [--repeats 2] [--json out.json]

A camera driver delivers a cloud tens of milliseconds after it was taken (exposure, transfer, the
driver's own processing); the service then decodes it. As in ``service_bench.py`` a feeder process
plays a recording over Zenoh on loopback (poses at 100 Hz stamped on schedule, sent when the feeder
gets to it, rendered clouds at 30 Hz, back and forth), here with each cloud published ``latency``
after its stamp. The service runs in
this process with the default config (wall clock, fusion in a worker process, compiled step) and
the recording's gripper convention. Every
published estimate is compared with the recording at the time of the poses it used (found by its
gripped vertices, which the poses set): the tracking error (two-way distance to the rope as rendered, as in
the tracking benchmarks) [mm], mean and p90 over the estimates after a settling time, and the mean
vertex distance to the markers.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.service_bench import frame_at, status  # noqa: E402
from benchmarks.service_timing import MODES, finish  # noqa: E402
from benchmarks.tracking.metric import rope_error  # noqa: E402

N_FRAMES = 500  # 5 s of the recording, played back and forth
SETTLE_S = 3.0  # estimates of the first seconds of a run are not scored (start, a new feeder)


def render_frames(path: Path, fps: float) -> None:
    """The recording's clouds, rendered once for every feeder run: ``path`` (.npz)."""
    from service import scenario

    positions, _ = scenario.demo_positions(N_FRAMES)
    frames = scenario.render(positions, 0.01, fps)
    cam = frames[0].camera
    np.savez(
        path,
        steps=np.array([f.step for f in frames]),
        xyz=np.stack([f.xyz for f in frames]),
        rgb=np.stack([f.rgb for f in frames]),
        K=np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]]),
        size=np.array([cam.width, cam.height]),
        world_from_camera=cam.world_from_camera,
    )


def feeder(endpoint: str, seconds: float, frames_path: str, latency_s: float) -> None:
    """Publish poses at 100 Hz stamped when sent and the clouds of ``frames_path`` stamped when
    taken, ``latency_s`` later; print the poses' (stamp, frame) as JSON at the end."""
    import zenoh

    from service import messages as M
    from service import scenario
    from service.config import ZenohSettings
    from service.geometry import matrix_to_pose, poses_from_vertices
    from service.node import open_session

    positions, _ = scenario.demo_positions(N_FRAMES)
    poses = poses_from_vertices(positions, scenario.offsets_for(positions))
    data = np.load(frames_path)
    frames = {int(k): i for i, k in enumerate(data["steps"])}
    xyz, rgb, K, (width, height) = data["xyz"], data["rgb"], data["K"], data["size"]
    camera_pose = matrix_to_pose(data["world_from_camera"])
    s = open_session(ZenohSettings(connect=[endpoint], multicast_scouting=False))
    drop = zenoh.CongestionControl.DROP
    pp = s.declare_publisher("deform/rod1/ee_poses", congestion_control=drop)
    pc = s.declare_publisher("deform/rod1/points", congestion_control=drop)
    pi = s.declare_publisher("deform/rod1/camera_info")
    pk = s.declare_publisher("deform/rod1/camera_pose")
    print("ready", flush=True)
    sent, due = [], []  # (stamp, frame); clouds waiting for their latency: (publish at, stamp, frame)
    t0, t0_ns = time.perf_counter(), time.time_ns()
    k = 0
    while time.perf_counter() - t0 < seconds:
        # stamped when measured, on schedule (as a robot's controller stamps its poses), sent when the
        # feeder gets to it: a busy feeder sends late and in bursts
        now, t = t0_ns + k * 10_000_000, time.perf_counter()
        if k % 100 == 0:
            pi.put(M.camera_info(now, K, int(width), int(height)))
            pk.put(M.pose_stamped(now, camera_pose))
        i = frame_at(k, N_FRAMES)
        pp.put(M.pose_array(now, poses[i]))
        sent.append((now, i))
        if i in frames:
            due.append((t + latency_s, now, frames[i]))
        while due and due[0][0] <= t + 1e-4:
            _, stamp, j = due.pop(0)
            pc.put(M.point_cloud(stamp, xyz[j], rgb[j]))
        k += 1
        delay = t0 + k * 0.01 - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    s.close()
    print(json.dumps(sent), flush=True)


def run_feeder(endpoint: str, seconds: float, frames_path: Path, latency_s: float) -> list[tuple[int, int]]:
    """The feeder as a process; returns what it sent: [(pose stamp, frame)]."""
    p = subprocess.Popen(
        [sys.executable, __file__, "--feeder", endpoint, "--feeder-s", str(seconds)]
        + ["--frames", str(frames_path), "--feeder-latency-s", str(latency_s)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert p.stdout.readline().strip() == "ready"
    out, _ = p.communicate(timeout=seconds + 120)
    return [tuple(e) for e in json.loads(out.strip().splitlines()[-1])]


def errors(estimates, sent, positions, grip_idx, from_ns: int) -> np.ndarray:
    """Per estimate after ``from_ns``, against the recording at the time of the poses it used: of
    the pairs of consecutive poses sent in the 60 ms before it, the one whose gripped vertices,
    interpolated, hold its own (it may have stepped to poses between two), and the rope interpolated
    the same way. (k, 2): the tracking error (two-way distance to the rope as rendered,
    :func:`benchmarks.tracking.metric.rope_error`) and the mean vertex distance to the markers [m]."""
    stamps = np.array([s for s, _ in sent])
    frames = np.array([f for _, f in sent])
    out = []
    for stamp, x in estimates:
        if stamp < from_ns:
            continue
        lo, hi = np.searchsorted(stamps, stamp - 60_000_000), np.searchsorted(stamps, stamp, side="right")
        best = None
        for j in range(lo, min(hi, len(frames) - 1)):
            g0, g1 = positions[frames[j]][grip_idx], positions[frames[j + 1]][grip_idx]
            d = g1 - g0
            a = float(np.clip(np.sum((x[grip_idx] - g0) * d) / max(np.sum(d * d), 1e-12), 0.0, 1.0))
            off = np.abs(g0 + a * d - x[grip_idx]).max()
            if best is None or off < best[0]:
                best = (off, j, a)
        if best is None:
            continue
        _, j, a = best
        truth = (1 - a) * positions[frames[j]] + a * positions[frames[j + 1]]
        out.append((rope_error(x, truth), np.linalg.norm(x - truth, axis=-1).mean()))
    return np.array(out).reshape(-1, 2)


def measure(mode: dict, latencies: list[float], run_s: float, frames_path: Path, positions) -> dict:
    """One service (the default config but ``mode``), a feeder run per latency."""
    import logging

    logging.basicConfig(level=logging.WARNING)
    from deform import gripped_indices
    from service.client import ShapeClient
    from service.config import load_config
    from service.demo import free_port
    from service.node import Service

    ep = f"tcp/127.0.0.1:{free_port()}"
    from service import scenario

    cfg = load_config(
        None,
        zenoh={"mode": "peer", "listen": [ep], "multicast_scouting": False},
        **mode,
        grippers=scenario.offsets_for(positions).model_dump(),  # the recording's, as the demo sets them
    )
    svc = Service(cfg).start()
    client = ShapeClient(connect=[ep], timeout_s=5.0)
    got, lock = [], threading.Lock()

    def on_estimate(stamp, x, _observed):
        with lock:
            got.append((stamp, np.asarray(x, dtype=float)))

    client.subscribe(on_estimate)
    # the predict worker compiles its rollout at start-up (a core for tens of seconds): wait for it too
    while not all((status(client) or {}).get(k) for k in ("predict_ready", "step_ready")):
        time.sleep(0.5)
    out = {}
    try:
        for latency in latencies:
            with lock:
                got.clear()
            s0 = status(client)
            sent = run_feeder(ep, run_s, frames_path, latency)
            s1 = status(client)
            with lock:
                estimates = list(got)
            settled = sent[0][0] + int(SETTLE_S * 1e9)
            e = errors(estimates, sent, positions, gripped_indices(len(positions[0])), settled)

            def grew(key: str, s0=s0, s1=s1) -> int:
                return s1["counts"].get(key, 0) - s0["counts"].get(key, 0)

            out[f"{round(1e3 * latency)}"] = {
                "error_mm": round(1e3 * float(e[:, 0].mean()), 2),
                "error_p90_mm": round(1e3 * float(np.percentile(e[:, 0], 90)), 2),
                "vertex_error_mm": round(1e3 * float(e[:, 1].mean()), 2),
                "estimates_scored": len(e),
                "clouds_fused": grew("clouds_fused"),
                "catchup_steps_per_cloud": round(
                    grew("fusion_catchup_steps") / max(grew("clouds_fused"), 1), 1
                ),
                "deadline_misses": grew("deadline_misses") + grew("ticks_skipped"),
                "ticks": grew("ticks"),
                "tick_to_publish_ms": s1["tick_to_publish_ms"],
                "fusion_ms": s1["fusion_ms"],
                "cloud_age_ms": s1.get("cloud_age_ms"),
                "dropped": s1["dropped"],
                "rope": s1.get("rope"),  # redetections, the camera's length over the model's, ...
            }
            print(mode, round(1e3 * latency), json.dumps(out[f"{round(1e3 * latency)}"]), flush=True)
    finally:
        client.close()
        svc.stop()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--latency-ms", type=float, nargs="+", default=[0.0, 50.0, 100.0])
    ap.add_argument("--run-s", type=float, default=20.0)
    ap.add_argument("--repeats", type=int, default=2, help="each mode's service this many times, alternated")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--modes", nargs="+", choices=list(MODES), default=list(MODES))
    ap.add_argument("--json")
    ap.add_argument("--feeder")
    ap.add_argument("--feeder-s", type=float)
    ap.add_argument("--feeder-latency-s", type=float, default=0.0)
    ap.add_argument("--frames")
    args = ap.parse_args()
    if args.feeder:
        feeder(args.feeder, args.feeder_s, args.frames, args.feeder_latency_s)
        return 0
    import tempfile

    from benchmarks.provenance import provenance
    from service import scenario

    positions, source = scenario.demo_positions(N_FRAMES)
    latencies = [ms / 1e3 for ms in args.latency_ms]
    out: dict = {**provenance(), "recording": source, "run_s": args.run_s, "fps": args.fps}
    runs: dict = {m: {} for m in args.modes}
    with tempfile.TemporaryDirectory() as tmp:
        frames_path = Path(tmp) / "frames.npz"
        render_frames(frames_path, args.fps)
        for _ in range(args.repeats):
            for mode in args.modes:
                for key, row in measure(MODES[mode], latencies, args.run_s, frames_path, positions).items():
                    runs[mode].setdefault(key, []).append(row)
    out["repeats"] = args.repeats
    out["modes"] = {
        mode: {
            key: {
                "error_mm": round(float(np.mean([r["error_mm"] for r in rows])), 2),
                "error_p90_mm": round(float(np.mean([r["error_p90_mm"] for r in rows])), 2),
                "runs": rows,
            }
            for key, rows in by_latency.items()
        }
        for mode, by_latency in runs.items()
    }
    finish(out, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
