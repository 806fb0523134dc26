"""How long `deform-service run` takes to be ready, cold and warm, and how the loop fares meanwhile.

    python benchmarks/service_startup.py [--runs 2] [--json benchmarks/results/service_startup.json]

Each run starts the service as a user does (``python -m service run --config ...``, a fresh process)
with a feeder publishing poses at 100 Hz and rendered clouds at 30 Hz (benchmarks/service_bench.py)
and a client, both started (and ready) before the service as on a robot, and watches it through the
client library (``ShapeClient``), timed from the service's launch: when the first vertices arrive, when
status says ``predict_ready`` and ``step_ready``, the loop's deadline misses and the longest gap of
the vertex stream until then, how fast a predict during warm-up is answered (``not_ready``), and
one 64 x 100 predict once ready. **cold**: empty compile caches (``DEFORM_CACHE`` and
``TORCHINDUCTOR_CACHE_DIR`` in a new temporary folder); **warm**: the same folders again.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def one_start(caches: Path, timeout_s: float, rod: str | None = None) -> dict:
    """One start of ``deform-service run [--rod ROD]`` on the compile caches in ``caches``."""
    from benchmarks.service_bench import start_feeder
    from service.client import NotReady, ServiceError, ShapeClient
    from service.config import load_config
    from service.demo import free_port
    from service.geometry import poses_from_vertices

    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg_path = caches / "service.yaml"
    cfg_path.write_text(json.dumps({"zenoh": {"listen": [ep], "multicast_scouting": False}}))
    env = dict(
        os.environ,
        DEFORM_CACHE=str(caches),
        TORCHINDUCTOR_CACHE_DIR=str(caches / "inductor"),
        PYTHONUNBUFFERED="1",
    )
    # the robot's feeds (poses, clouds) and the client run before the service starts, as on a robot:
    # the feeder's own start-up (rendering, seconds) must not be counted, nor slow the service's
    feed = start_feeder(ep, timeout_s + 60, 30.0)
    arrivals: list[float] = []
    lock = threading.Lock()

    def on_vertices(stamp_ns, x, observed):
        with lock:
            arrivals.append(time.perf_counter())

    out: dict = {}
    proc = None
    try:
        with ShapeClient(connect=[ep], timeout_s=1.0) as rope:
            rope.subscribe(on_vertices)
            t0 = time.perf_counter()
            proc = subprocess.Popen(
                [sys.executable, "-m", "service", "run", "--config", str(cfg_path)]
                + (["--rod", rod] if rod else []),
                cwd=ROOT,
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            )
            status, not_ready_ms = None, []
            while time.perf_counter() - t0 < timeout_s:
                try:
                    status = rope.status()
                except ServiceError:
                    time.sleep(0.2)
                    continue
                out.setdefault("status_s", round(time.perf_counter() - t0, 1))
                if arrivals and "first_vertices_s" not in out:
                    out["first_vertices_s"] = round(arrivals[0] - t0, 1)
                if not status["predict_ready"] and arrivals and len(not_ready_ms) < 5:
                    plans = np.tile(
                        poses_from_vertices(rope.vertices()[1].astype(float), load_config().grippers),
                        (4, 10, 1, 1),
                    )
                    t = time.perf_counter()
                    try:
                        rope.predict(plans, timeout_s=30.0)
                    except NotReady:
                        not_ready_ms.append(1e3 * (time.perf_counter() - t))
                for k in ("predict_ready", "step_ready"):
                    if status[k] and f"{k}_s" not in out:
                        out[f"{k}_s"] = round(time.perf_counter() - t0, 1)
                if status["predict_ready"] and status["step_ready"] and arrivals:  # serving, compiled
                    break
                if status.get("predict_state") == "failed":  # final: it will not become ready
                    break
                time.sleep(0.2)
            t_ready = time.perf_counter()
            out["ready_s"] = round(t_ready - t0, 1) if status and not status["not_ready"] else None
            for k in ("predict_state", "predict_mode", "predict_failed", "step"):
                out[k] = (status or {}).get(k)
            counts = (status or {}).get("counts", {})
            ticks, misses, skipped = (counts.get(k, 0) for k in ("ticks", "deadline_misses", "ticks_skipped"))
            out["warmup_loop"] = {
                "ticks": ticks,
                "deadline_misses": misses,
                "ticks_skipped": skipped,
                "miss_pct": round(100.0 * (misses + skipped) / max(ticks + skipped, 1), 2),
                "step": (status or {}).get("step"),
            }
            with lock:
                gaps = np.diff([a for a in arrivals if a <= t_ready])
            out["warmup_vertex_gap_max_ms"] = round(1e3 * float(gaps.max()), 1) if len(gaps) else None
            out["not_ready_reply_ms"] = [round(v, 1) for v in not_ready_ms]
            if out["ready_s"] is not None:
                plans = np.tile(
                    poses_from_vertices(rope.vertices()[1].astype(float), load_config().grippers),
                    (64, 100, 1, 1),
                )
                t = time.perf_counter()
                rope.predict(plans, timeout_s=120.0)
                out["first_predict_64x100_ms"] = round(1e3 * (time.perf_counter() - t), 1)
    finally:
        feed.kill()
        err = ""
        if proc is not None:
            proc.terminate()
            try:
                _, err = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
    out["log_tail"] = [line for line in (err or "").splitlines() if "ready" in line or "compiled" in line][
        -4:
    ]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=2, help="cold + warm pairs")
    ap.add_argument("--timeout-s", type=float, default=400.0)
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/service_startup.json"))
    args = ap.parse_args()
    from benchmarks.provenance import provenance

    result = {
        **provenance(),
        "runs": [],
    }
    for i in range(args.runs):
        with tempfile.TemporaryDirectory(prefix="deform-startup-") as tmp:
            for kind in ("cold", "warm"):
                row = dict(kind=kind, run=i, **one_start(Path(tmp), args.timeout_s))
                print(json.dumps(row), flush=True)
                result["runs"].append(row)

    def med(kind, key):
        vals = [r[key] for r in result["runs"] if r["kind"] == kind and r.get(key) is not None]
        return float(np.median(vals)) if vals else None

    result["summary"] = {
        kind: {
            "ready_s": med(kind, "ready_s"),
            "predict_ready_s": med(kind, "predict_ready_s"),
            "step_ready_s": med(kind, "step_ready_s"),
            "warmup_miss_pct": float(
                np.median([r["warmup_loop"]["miss_pct"] for r in result["runs"] if r["kind"] == kind])
            ),
            "warmup_vertex_gap_max_ms": med(kind, "warmup_vertex_gap_max_ms"),
            "first_predict_64x100_ms": med(kind, "first_predict_64x100_ms"),
        }
        for kind in ("cold", "warm")
    }
    print(json.dumps(result["summary"], indent=1))
    Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
