"""Service benchmark: the live 100 Hz loop with clouds at 30 Hz, tick-to-publish latency, predict for
64 plans x 100 steps, and a memory soak.

    .venv/bin/python benchmarks/service_bench.py [--loop-s 30] [--soak-s 1800] [--json out.json]

The robot and the camera are simulated by a separate feeder process publishing over Zenoh on
loopback (poses at 100 Hz, rendered clouds at 30 Hz, playing a recording forward and backward), so
the service process is measured alone, as deployed. Use ``--soak-s 120`` for a short soak.

Why forward and backward: played in a loop, the 300-frame demo recording jumps back to its first
frame every 3 s, and one gripper with it, by 24 cm in one tick (24 m/s; the recording itself moves a
gripper at most 6.4 mm per frame). No robot does that, and each jump left the loop's model step
unconverged for several ticks. ``--loop-jumps`` restores the loop (the benchmark until 2026-11-23).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def frame_at(k: int, n_frames: int, loop_jumps: bool = False) -> int:
    """The recording's frame for tick ``k``: forward then backward (continuous), or in a loop."""
    if loop_jumps:
        return k % n_frames
    i = k % (2 * (n_frames - 1))
    return i if i < n_frames else 2 * (n_frames - 1) - i


def feeder(endpoint: str, seconds: float, fps: float, loop_jumps: bool = False) -> None:
    """Publish poses at 100 Hz and clouds at ``fps`` with the current time as stamp, back and forth
    over the recording (see the module docstring)."""
    from service import messages as M
    from service import scenario
    from service.config import ZenohSettings
    from service.geometry import poses_from_vertices
    from service.node import open_session

    positions, _ = scenario.demo_positions(300)
    grippers = scenario.offsets_for(positions)
    frames = scenario.render(positions, 0.01, fps)
    poses = poses_from_vertices(positions, grippers)
    s = open_session(ZenohSettings(connect=[endpoint], multicast_scouting=False))
    import zenoh

    pp = s.declare_publisher("deform/rod1/ee_poses", congestion_control=zenoh.CongestionControl.DROP)
    pc = s.declare_publisher("deform/rod1/points", congestion_control=zenoh.CongestionControl.DROP)
    pi = s.declare_publisher("deform/rod1/camera_info")
    pk = s.declare_publisher("deform/rod1/camera_pose")
    from service.geometry import matrix_to_pose

    cam = frames[0].camera
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    by_step = {f.step: f for f in frames}
    print("ready", flush=True)
    t0 = time.perf_counter()
    k = 0
    while time.perf_counter() - t0 < seconds:
        now = time.time_ns()
        if k % 100 == 0:
            pi.put(M.camera_info(now, K, cam.width, cam.height))
            pk.put(M.pose_stamped(now, matrix_to_pose(cam.world_from_camera)))
        i = frame_at(k, len(positions), loop_jumps)
        pp.put(M.pose_array(now, poses[i]))
        if i in by_step:
            f = by_step[i]
            pc.put(M.point_cloud(now, f.xyz, f.rgb))
        k += 1
        delay = t0 + k * 0.01 - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    s.close()


def _rss_kb(pid) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS"):
                    return int(line.split()[1])
    except FileNotFoundError:
        pass
    return 0


def rss_mb(svc) -> float:
    """Resident memory of the service: this process plus its worker processes (fusion, predict)."""
    pids = [w.pid for w in (svc.fusion_worker, *svc.predict_worker.workers) if hasattr(w, "pid")]
    return (_rss_kb("self") + sum(_rss_kb(p) for p in pids)) / 1024


def counted(s0: dict, s1: dict, key: str) -> int:
    """How much the status counter ``key`` grew between two status snapshots."""
    return s1["counts"].get(key, 0) - s0["counts"].get(key, 0)


def status(client) -> dict | None:
    """The service status through the client library (None while it does not answer)."""
    from service.client import ServiceError

    try:
        return client.status(timeout_s=5.0)
    except ServiceError:
        return None


def start_feeder(endpoint: str, seconds: float, fps: float, loop_jumps: bool = False):
    p = subprocess.Popen(
        [sys.executable, __file__, "--feeder", endpoint, "--feeder-s", str(seconds), "--fps", str(fps)]
        + (["--loop-jumps"] if loop_jumps else []),
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert p.stdout.readline().strip() == "ready"
    return p


def predict_run(endpoint: str, n: int, stale_plans: bool = False) -> None:
    """Client process: ``n`` predict queries of 64 random plans x 100 steps; prints the timings as JSON.

    As a planner does, each request's plans start at the grippers' current poses: the client asks for
    the latest estimate (``{ns}/vertices``, outside the timed part) before building them.
    ``stale_plans``: every plan starts where the grippers were when the client started (the benchmark
    until 2026-11-23): while the rod moves, each plan then opens with a gripper jump of centimetres.
    """
    from service.client import ShapeClient
    from service.config import load_config
    from service.geometry import poses_from_vertices

    rope = ShapeClient(connect=[endpoint], timeout_s=5.0)
    grippers = load_config().grippers

    def current_poses():
        return poses_from_vertices(rope.vertices()[1].astype(float), grippers)

    base = current_poses()
    rng = np.random.default_rng(0)
    times = []
    for _ in range(n):
        if not stale_plans:
            base = current_poses()
        plans = base[None, None] + np.linspace(0, 1, 100)[None, :, None, None] * np.concatenate(
            [rng.uniform(-0.1, 0.1, (64, 1, 2, 3)), np.zeros((64, 1, 2, 4))], axis=-1
        )
        # timed as a planner sees it: request encoded (orjson), sent, answered, decoded
        t = time.perf_counter()
        rope.predict_full(plans, dt=0.01, timeout_s=60.0)
        times.append(1e3 * (time.perf_counter() - t))
        time.sleep(0.2)  # a planner asking about five times a second
    print(
        json.dumps(
            {
                "ms": [round(t, 1) for t in times],
                "p50_ms": round(float(np.median(times)), 1),
                "p90_ms": round(float(np.percentile(times, 90)), 1),
                "max_ms": round(float(np.max(times)), 1),
                "reply": "binary float32 (service/predict_codec.py), ShapeClient.predict_full",
            }
        ),
        flush=True,
    )
    rope.close()


def predict_client(endpoint: str, n: int, stale_plans: bool = False) -> dict:
    p = subprocess.run(
        [sys.executable, __file__, "--predict-client", endpoint, "--predict-n", str(n)]
        + (["--stale-plans"] if stale_plans else []),
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    lines = [l for l in p.stdout.splitlines() if l.startswith("{")]
    if not lines:
        raise RuntimeError(f"predict client failed: {p.stderr[-2000:]}")
    return json.loads(lines[-1])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--loop-s", type=float, default=30.0)
    ap.add_argument("--soak-s", type=float, default=1800.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--predict-n", type=int, default=20, help="predict queries per condition")
    ap.add_argument("--json")
    ap.add_argument("--feeder")
    ap.add_argument("--config", help="service YAML (default: config/service.yaml)")
    ap.add_argument("--predict-client")
    ap.add_argument("--feeder-s", type=float)
    ap.add_argument(
        "--loop-jumps",
        action="store_true",
        help="play the recording in a loop (a 24 cm gripper jump every 3 s) instead of back and forth",
    )
    ap.add_argument(
        "--stale-plans",
        action="store_true",
        help="plans start where the grippers were when the client started, not at their current poses",
    )
    args = ap.parse_args()
    if args.predict_client:
        predict_run(args.predict_client, args.predict_n, args.stale_plans)
        return 0
    if args.feeder:
        feeder(args.feeder, args.feeder_s, args.fps, args.loop_jumps)
        return 0

    import logging

    logging.basicConfig(level=logging.WARNING)
    from service.client import ShapeClient
    from service.config import load_config
    from service.demo import free_port
    from service.node import Service

    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg = load_config(args.config, zenoh={"mode": "peer", "listen": [ep], "multicast_scouting": False})
    svc = Service(cfg).start()
    client = ShapeClient(connect=[ep], timeout_s=5.0)
    from benchmarks.provenance import provenance

    out: dict = {
        **provenance(),
        "tracker": type(svc.est.tracker).__name__,
        "feeder": "loop (gripper jumps)" if args.loop_jumps else "back and forth",
    }

    t_ready = time.perf_counter()
    # the predict worker compiles its rollout, and the service its loop step, first
    while not all((status(client) or {}).get(k) for k in ("predict_ready", "step_ready")):
        time.sleep(0.5)
    out["predict_warmup_s"] = round(time.perf_counter() - t_ready, 1)
    out["workers"] = cfg.workers.model_dump()
    out["loop_step"] = (status(client) or {}).get("step")

    # 1. live loop with clouds at 30 Hz
    feed = start_feeder(ep, args.loop_s + 3, args.fps, args.loop_jumps)
    time.sleep(3.0)  # initialization and warm-up
    s0 = status(client)
    time.sleep(args.loop_s)
    s1 = status(client)
    feed.wait()
    ticks = s1["counts"]["ticks"] - s0["counts"]["ticks"]
    misses = counted(s0, s1, "deadline_misses")
    skipped = counted(s0, s1, "ticks_skipped")
    fused = counted(s0, s1, "clouds_fused")
    redone = s1.get("step_redone", 0) - s0.get("step_redone", 0)
    out["loop"] = {
        "seconds": args.loop_s,
        "ticks": ticks,
        "deadline_misses": misses,
        "ticks_skipped": skipped,
        "deadline_miss_pct": round(100.0 * (misses + skipped) / max(ticks + skipped, 1), 3),
        "rate_hz": s1["rate_hz"],
        "clouds_fused": fused,
        "compiled_steps_redone": redone,
        "clouds_per_s": round(fused / args.loop_s, 1),
        "step_ms": s1["step_ms"],
        "tick_to_publish_ms": s1["tick_to_publish_ms"],
        "fusion_ms": s1["fusion_ms"],
        "dropped": s1["dropped"],
        "rejected": s1["rejected"],
    }
    print(json.dumps(out["loop"]), flush=True)

    # 2. predict 64 plans x 100 steps from the current estimate, asked by a separate client process
    #    (a planner is its own process; in this one its JSON work would compete with the loop)
    def inside(n: int) -> dict:
        """The last ``n`` predictions as the service saw them: job handed to the predict worker ->
        reply back (IPC included), and the time inside the worker (parse, rollout, encode)."""
        return {
            "service_ms": svc.stats.predict_s.summary(last=n),
            "worker_ms": svc.stats.predict_compute_s.summary(last=n),
        }

    out["plans_start"] = (
        "where the grippers were at client start" if args.stale_plans else "current gripper poses"
    )
    s0 = status(client)
    out["predict_64x100"] = dict(
        predict_client(ep, args.predict_n, args.stale_plans),
        **inside(args.predict_n),
        steps_redone=counted(s0, status(client), "predict_steps_redone"),
        note="service idle (no feeder); request sent to reply received, client process",
    )
    print(json.dumps(out["predict_64x100"]), flush=True)
    feed = start_feeder(ep, 3 + args.predict_n * 1.0 + 60, args.fps, args.loop_jumps)
    time.sleep(3.0)
    s0, t_live0 = status(client), time.perf_counter()
    live = predict_client(ep, args.predict_n, args.stale_plans)
    s1, t_live1 = status(client), time.perf_counter()
    feed.kill()
    out["predict_64x100_live"] = dict(
        live,
        **inside(args.predict_n),
        steps_redone=counted(s0, s1, "predict_steps_redone"),
        loop_deadline_misses=counted(s0, s1, "deadline_misses"),
        clouds_fused=counted(s0, s1, "clouds_fused"),
        fusions_deferred=counted(s0, s1, "fusion_deferred"),
        seconds=round(t_live1 - t_live0, 1),
        loop_ticks=s1["counts"]["ticks"] - s0["counts"]["ticks"],
        note="while the loop runs at 100 Hz with clouds at 30 Hz; client process",
    )
    print(json.dumps(out["predict_64x100_live"]), flush=True)

    # 3. memory soak
    feed = start_feeder(ep, args.soak_s + 10, args.fps, args.loop_jumps)
    time.sleep(min(60.0, max(10.0, args.soak_s / 10)))
    samples = [(0.0, rss_mb(svc))]
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < args.soak_s:
        time.sleep(min(10.0, args.soak_s / 10))
        samples.append((round(time.perf_counter() - t0, 1), rss_mb(svc)))
    s2 = status(client)
    feed.kill()
    growth = 100.0 * (samples[-1][1] - samples[0][1]) / samples[0][1]
    out["soak"] = {
        "seconds": args.soak_s,
        "rss_start_mb": round(samples[0][1], 1),
        "rss_end_mb": round(samples[-1][1], 1),
        "growth_pct": round(growth, 2),
        "samples": [(t, round(m, 1)) for t, m in samples],
        "ticks": s2["ticks"],
        "deadline_misses_total": s2["deadline_misses"],
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }
    print(json.dumps({k: v for k, v in out["soak"].items() if k != "samples"}), flush=True)
    client.close()
    svc.stop()
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
