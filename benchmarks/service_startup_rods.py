"""Each shipped rod's first `deform-service run --rod DLOk` after `make install`: prebuild, then start.

    python benchmarks/service_startup_rods.py [--rods DLO1 DLO4] [--runs 2] [--cache DIR] [--json benchmarks/results/service_startup_rods.json]

What ``make install`` leaves is rebuilt in a new cache folder (``DEFORM_CACHE`` and
``TORCHINDUCTOR_CACHE_DIR``): ``python -m service prebuild --rod DLOk`` for every rod (the same as
``--all-rods``, timed per rod). Then each rod is started once on that cache as a user does, with a
feeder and a client started before it (``benchmarks/service_startup.py``'s ``one_start``): when
status says ``predict_ready`` and ``step_ready``, how predict and the loop run (``compiled`` from
the prebuilt packages, else what the start had to do), and one 64 x 100 predict once ready.
The target (issue 52): every rod ``predict_ready`` within 10 s. ``--cache DIR``: that folder
instead of a new one (kept; a prebuild of packages already in it only checks them), e.g. to time
the starts again; each start records the machine's load average, which moves them by seconds on
two cores.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

TARGET_S = 10.0


def prebuild(caches: Path, rods: list[str]) -> dict:
    """``python -m service prebuild --rod ROD`` for each rod into ``caches``: -> seconds per rod
    and in all."""
    env = dict(os.environ, DEFORM_CACHE=str(caches), TORCHINDUCTOR_CACHE_DIR=str(caches / "inductor"))
    per_rod = {}
    t_all = time.perf_counter()
    for rod in rods:
        t = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "service", "prebuild", "--rod", rod], cwd=ROOT, env=env, check=True
        )
        per_rod[rod] = round(time.perf_counter() - t, 1)
        print(json.dumps({"prebuild": rod, "s": per_rod[rod]}), flush=True)
    return {"per_rod_s": per_rod, "total_s": round(time.perf_counter() - t_all, 1)}


def main() -> int:
    from benchmarks.provenance import provenance
    from benchmarks.service_startup import one_start
    from service.cli import shipped_rods

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rods", nargs="+", default=None, help="default: every shipped model")
    ap.add_argument("--runs", type=int, default=2, help="starts of each rod (in rounds over the rods)")
    ap.add_argument("--timeout-s", type=float, default=400.0)
    ap.add_argument("--cache", help="compile caches to use and keep (default: a new temporary folder)")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/service_startup_rods.json"))
    args = ap.parse_args()
    rods = args.rods or shipped_rods()
    result = {**provenance(), "target_predict_ready_s": TARGET_S}
    with tempfile.TemporaryDirectory(prefix="deform-startup-rods-") as tmp:
        caches = Path(args.cache or tmp)
        result["prebuild"] = prebuild(caches, rods)
        result["runs"] = []
        for i in range(args.runs):
            for rod in rods:
                load = round(os.getloadavg()[0], 2)  # other programs' load when the start begins
                row = dict(rod=rod, run=i, load_avg_1min=load, **one_start(caches, args.timeout_s, rod))
                print(json.dumps(row), flush=True)
                result["runs"].append(row)

    def per_rod(rod: str, key: str) -> list:
        return [r.get(key) for r in result["runs"] if r["rod"] == rod]

    result["summary"] = {
        rod: {
            **{
                key: per_rod(rod, key)
                for key in ("predict_ready_s", "step_ready_s", "first_predict_64x100_ms", "load_avg_1min")
            },
            "predict_mode": sorted({str(m) for m in per_rod(rod, "predict_mode")}),
            "step": sorted({str(m) for m in per_rod(rod, "step")}),
        }
        for rod in rods
    }
    result["all_within_target"] = all(
        (r.get("predict_ready_s") or float("inf")) <= TARGET_S
        and r.get("first_predict_64x100_ms") is not None
        for r in result["runs"]
    )
    print(json.dumps({"prebuild": result["prebuild"], "summary": result["summary"]}, indent=1))
    Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
