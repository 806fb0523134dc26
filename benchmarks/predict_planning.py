"""Planning-scale predict in the service (issue 21): request to reply at a client, while the loop runs.

    python benchmarks/predict_planning.py [--n 20] [--json benchmarks/results/predict_planning.json]

One service (default config, except limits raised to 1024 plans and predict warmed up for 64, 256
and 1024 plans), a feeder publishing poses at 100 Hz and clouds at 30 Hz, and a client process
(``ShapeClient``, binary requests and replies) asking in turn, ``--n`` times each:
1024 plans x 100 steps in cost mode (only the P costs come back), 256 x 100 final shapes only, and
64 x 100 all steps. Plans start at the grippers' current poses and move each gripper up to 10 cm
per axis. The loop's misses and tick-to-publish p99 over the whole run are reported beside.

``--compare predict_dtype=float64 predict_threads=1`` also runs the service with each of these
``workers`` settings changed (one at a time) in the same run: a service per (round, variant), rounds
interleaved (``--rounds``) because the VM's speed drifts; the default configuration is the headline,
the variants are reported beside with the ratio of their p50s to it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

CASES = (("1024x100 cost", 1024, "none"), ("256x100 final", 256, "final"), ("64x100 all", 64, "all"))


def client(endpoint: str, n: int) -> None:
    """The planner's process: prints one JSON line of timings."""
    from service.client import ShapeClient
    from service.config import load_config
    from service.geometry import poses_from_vertices

    rope = ShapeClient(connect=[endpoint], timeout_s=5.0)
    grippers = load_config().grippers
    rng = np.random.default_rng(0)
    times = {label: [] for label, _, _ in CASES}
    for _ in range(n):
        for label, P, ret in CASES:
            x = rope.vertices()[1].astype(float)
            base = poses_from_vertices(x, grippers)
            plans = base[None, None] + np.linspace(0, 1, 100)[None, :, None, None] * np.concatenate(
                [rng.uniform(-0.1, 0.1, (P, 1, 2, 3)), np.zeros((P, 1, 2, 4))], axis=-1
            )
            cost = {"goal": x, "weights": {"goal": 1.0, "stretch": 1.0}} if ret == "none" else None
            t = time.perf_counter()
            out = rope.predict_full(plans, steps=ret, cost=cost, timeout_s=120.0)
            times[label].append(1e3 * (time.perf_counter() - t))
            assert (out.costs is not None) if ret == "none" else out.vertices.shape[0] == P
            time.sleep(0.2)
    print(json.dumps(times), flush=True)
    rope.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/predict_planning.json"))
    ap.add_argument("--client")
    ap.add_argument("--compare", nargs="*", default=[], help="workers settings KEY=VALUE, one per variant")
    ap.add_argument("--rounds", type=int, default=1, help="services per variant, interleaved")
    args = ap.parse_args()
    if args.client:
        client(args.client, args.n)
        return 0
    import logging

    logging.basicConfig(level=logging.WARNING)
    from benchmarks.service_bench import start_feeder, status
    from service.client import ShapeClient
    from service.config import load_config
    from service.demo import free_port
    from service.node import Service

    def one_service(workers: dict, n: int) -> dict:
        ep = f"tcp/127.0.0.1:{free_port()}"
        cfg = load_config(
            zenoh={"listen": [ep], "multicast_scouting": False},
            limits={"max_plans": 1024, "max_plan_steps_total": 102400, "max_request_bytes": 16_000_000},
            workers={"predict_warmup": [64, 256, 1024], **workers},
        )
        svc = Service(cfg).start()
        rope = ShapeClient(connect=[ep], timeout_s=5.0)
        t0 = time.perf_counter()

        def ready() -> bool:  # every predict process too (the others start after the first is ready)
            s = status(rope) or {}
            up = s.get("predict_processes", 1) >= cfg.workers.predict_processes
            return bool(s.get("predict_ready") and s.get("step_ready") and up)

        while not ready():
            time.sleep(0.5)
        warmup = time.perf_counter() - t0
        feed = start_feeder(ep, 3600, 30.0)
        time.sleep(3.0)
        s0 = status(rope)
        p = subprocess.run(
            [sys.executable, __file__, "--client", ep, "--n", str(n)],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=3600,
        )
        s1 = status(rope)
        # the service's own timings of the same requests (the client asks the cases in turn):
        # handed to the predict processes -> reply assembled, and the slowest share inside its process
        served = s1["counts"].get("predictions", 0) - s0["counts"].get("predictions", 0)
        inside = {}
        if served == len(CASES) * n:
            handled, computed = (
                r.values(last=served) for r in (svc.stats.predict_s, svc.stats.predict_compute_s)
            )
            inside = {
                label: {"service": handled[i :: len(CASES)], "worker": computed[i :: len(CASES)]}
                for i, (label, _, _) in enumerate(CASES)
            }
        feed.kill()
        rope.close()
        svc.stop()
        lines = [line for line in p.stdout.splitlines() if line.startswith("{")]
        if not lines:
            raise SystemExit(f"client failed: {p.stderr[-2000:]}")
        misses = sum(
            s1["counts"].get(k, 0) - s0["counts"].get(k, 0) for k in ("deadline_misses", "ticks_skipped")
        )
        return {
            "warmup_s": warmup,
            "times": json.loads(lines[-1]),
            "inside": inside,
            "ticks": s1["counts"]["ticks"] - s0["counts"]["ticks"],
            "misses": misses,
            "tick_to_publish_ms": s1["tick_to_publish_ms"],
            "rod_steps_redone": s1["counts"].get("predict_steps_redone", 0)
            - s0["counts"].get("predict_steps_redone", 0),
            "rod_steps": sum(P * 100 for _, P, _ in CASES) * n,
        }

    per_round = max(1, args.n // args.rounds)
    defaults = load_config().workers
    cfg_workers = defaults.model_dump()
    variants = {"default": {}}
    for item in args.compare:
        key, value = item.split("=", 1)
        variants[item] = {key: yaml.safe_load(value)}
    runs: dict[str, list[dict]] = {name: [] for name in variants}
    for _ in range(args.rounds):
        for name, workers in variants.items():
            runs[name].append(one_service(workers, per_round))

    def summary(rs: list[dict]) -> dict:
        times = {label: [t for r in rs for t in r["times"][label]] for label in rs[0]["times"]}
        ticks, misses = sum(r["ticks"] for r in rs), sum(r["misses"] for r in rs)
        return {
            "warmup_s": round(rs[0]["warmup_s"], 1),
            "requests": {
                label: {
                    "p50_ms": round(float(np.median(v)), 1),
                    "p90_ms": round(float(np.percentile(v, 90)), 1),
                    "max_ms": round(float(np.max(v)), 1),
                    "n": len(v),
                }
                for label, v in times.items()
            },
            # where a request's time goes (p50s): the client's whole request, the service's handling
            # (split, the processes' pipes, assembly) and the slowest share's parse, rollout and encode
            "inside_p50_ms": {
                label: {
                    part: round(1e3 * float(np.median(v)), 1)
                    for part in ("service", "worker")
                    if (v := [t for r in rs for t in r["inside"].get(label, {}).get(part, [])])
                }
                for label in times
            },
            "redone_pct_of_rod_steps": round(
                100.0 * sum(r["rod_steps_redone"] for r in rs) / sum(r["rod_steps"] for r in rs), 3
            ),
            "loop": {
                "ticks": ticks,
                "miss_pct": round(100.0 * misses / max(ticks, 1), 3),
                "tick_to_publish_ms": rs[-1]["tick_to_publish_ms"],
            },
        }

    head = summary(runs["default"])
    from benchmarks.provenance import provenance

    out = {
        **provenance(),
        "workers": cfg_workers,
        "rounds": args.rounds,
        "warmup_s": head["warmup_s"],
        "requests": head["requests"],
        "inside_p50_ms": head["inside_p50_ms"],
        "redone_pct_of_rod_steps": head["redone_pct_of_rod_steps"],
        "targets_p50_ms": {"1024x100 cost": 300, "256x100 final": 100, "64x100 all": 100},
        "loop": head["loop"],
    }
    for name in list(variants)[1:]:
        other = summary(runs[name])
        out.setdefault("compared", {})[name] = {
            **other,
            "p50_ratio_to_headline": {
                label: round(other["requests"][label]["p50_ms"] / head["requests"][label]["p50_ms"], 2)
                for label in head["requests"]
            },
        }
    print(json.dumps(out, indent=1))
    Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
